"""The text files of an evaluation -- ``summary.md``, ``results.csv``, ``subjects.csv``,
``results.json`` -- and the words and limits its figures and ``report.html`` share with them.

``summary.md`` is laid out like the paper's Table 3: per registration, the generalized
overlap (inverse-volume, and inverse-volume & complexity weighting) and the specificity with
its standard error, each with its rank and quantitative relative rank.

The functions take an :class:`~itk_nrreval.evaluation.EvaluationResult` without importing its
class (:mod:`itk_nrreval.evaluation` calls this package to write: that import would be a
cycle).
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

import numpy as np

from ..measures.subject_qc import ranked, registration_flags
from ._format import format_number, format_percent

__all__ = [
    "FLAGGED_SUBJECTS_SHOWN",
    "SUBJECT_FLAG_WORDS",
    "CONCERN_WORDS",
    "concern_text",
    "WORST_NAMED",
    "TABLE_OVERLAPS",
    "TIES_WORDS",
    "ORDER_WORDS",
    "format_rank",
    "frame_spread_words",
    "frame_spread_flagged",
    "specificity_units",
    "summary_table",
    "subjects_summary",
    "subjects_csv",
    "results_csv",
    "results_json",
    "METRICS_DEFORMATION",
    "deformation_metrics",
    "metrics_csv",
]


#: How many flagged subjects per registration the HTML report shows with pictures (worst
#: first, by concern; how many more there are is said): the pipeline keeps a resampled slice of
#: these only, so the report stays light whatever the number of subjects.
FLAGGED_SUBJECTS_SHOWN = 6

TABLE_OVERLAPS = (
    ("overlap.inverse_volume", "Overlap (inverse volume)"),
    ("overlap.inverse_volume_complexity", "Overlap (inverse volume & complexity)"),
)


def format_rank(result, measure: str, name: str) -> str:
    """The rank of `name` by `measure` for a reader: ``"2"``, ``"1 (tied)"``, or a dash."""
    rank = result.ranks[measure][name]
    if rank is None:
        return "–"
    return f"{rank} (tied)" if result.tied_with(measure, name) else str(rank)


#: How the reports explain the relative rank and its ties (summary.md and report.html).
TIES_WORDS = (
    "Scores not told apart are tied: two registrations whose subject-level 95% interval "
    "of the difference includes 0 (not separable: the verdict's test), or, where no such "
    "interval was computed, whose difference is within 1.96 combined standard errors (the "
    "Monte-Carlo s.e. for specificity, the s.e. for generalization). In score order, ties "
    "chain through neighbours, but never across a separable pair: two registrations whose "
    "difference is separable never share a rank. Tied scores share the better rank, marked "
    "(tied), and one relative rank, that of their mean, so a spread within the noise is "
    "never shown as the whole 0-100% range; when every score is tied, all are 100%."
)

#: How the reports say in which order they list the registrations (the verdict's).
ORDER_WORDS = (
    "Rows in the verdict's order: the better of every decided pair above the worse, and "
    "where the decisions leave a choice, the lower specificity first (only the decided "
    "pairs listed in results.json are claims; verdict.ranking there is this order)."
)


def frame_spread_words(result) -> tuple[float | None, str]:
    """The mean frame spread (mm) that is flagged, and the reports' sentence saying so.

    The limit is :func:`itk_nrreval.io.plausibility.frame_spread_limit_mm` of the run's
    thresholds and field of view, the number :func:`~itk_nrreval.io.plausibility.flags` used;
    None (and a sentence without a number) for a result that does not record them.
    """
    from ..io.plausibility import Thresholds, frame_spread_limit_mm

    o = result.options
    fov = o.get("field_of_view_mm")
    fraction = o.get("thresholds", {}).get("frame_spread_fraction")
    if fov is None or fraction is None:
        return None, (
            "A mean spread above the flag threshold (frame_spread_fraction of the field "
            "of view) is flagged: comparing that registration in the common frame is doubtful."
        )
    limit = frame_spread_limit_mm(fov, Thresholds(frame_spread_fraction=fraction))
    return limit, (
        f"A mean spread above {format_number(limit, 3)} mm ({format_number(100 * fraction, 3)}% "
        f"of the {format_number(fov, 4)} mm field of view, the flag threshold) is flagged: the "
        "images do not agree where that registration's frame sits, and comparing it in the "
        "common frame is doubtful. Below it the spread is not judged. The max spread, the "
        "farthest estimate at a single voxel of a single image, is shown for context and "
        "not judged."
    )


def frame_spread_flagged(result, name: str) -> bool:
    """Whether `name`'s mean frame spread is above the limit of :func:`frame_spread_words`."""
    limit, _ = frame_spread_words(result)
    spread = result.scores[name].frame.spread_mean_mm
    return limit is not None and math.isfinite(spread) and spread > limit


def specificity_units(result) -> str:
    """The unit of specificity and generalization, e.g. ``"L1 distance, intensity units"``."""
    o = result.options
    exponent = next(iter(result.scores.values())).specificity.exponent
    unit = "intensity units" if exponent == 1 else f"(intensity units)^{exponent:g}"
    return f"{o['distance'].upper()} distance, {unit}"


def _ci(s, measure: str) -> str:
    iv = s.intervals.get(measure)
    if iv is None or not math.isfinite(iv.lo):
        return "–"
    return f"[{format_number(iv.lo)}, {format_number(iv.hi)}]"


def summary_table(result) -> str:
    """The verdict in words, then a Markdown table like the paper's Table 3.

    Columns: for each overlap weighting present among inverse volume and inverse volume &
    complexity, then specificity and generalization: score, subject-level 95% interval,
    rank and relative rank (specificity also its Monte-Carlo standard error); then the
    plausibility flags. Lower is better for specificity and generalization, higher for
    overlap. A second table gives each registration's frame and deformation plausibility.
    """
    cols = [(m, title) for m, title in TABLE_OVERLAPS if m in result.ranks]
    header = ["Registration"]
    for _, title in cols:
        header += [f"{title}", "95% CI", "Rank", "Rel. rank"]
    header += ["Specificity", "95% CI", "MC s.e.", "Rank", "Rel. rank"]
    header += ["Generalization", "95% CI", "Rank", "Rel. rank", "Flags"]
    order = list(result.verdict.ranking) if result.verdict is not None else list(result.scores)
    rows = []
    for name in order:
        s = result.scores[name]
        row = [name]
        for m, _ in cols:
            row += [
                format_number(s.measures()[m]),
                _ci(s, m),
                format_rank(result, m, name),
                format_percent(result.relative_ranks[m][name]),
            ]
        row += [
            format_number(s.specificity.value),
            _ci(s, "specificity"),
            format_number(s.specificity.stderr, 2),
            format_rank(result, "specificity", name),
            format_percent(result.relative_ranks["specificity"][name]),
        ]
        row += [
            format_number(s.generalization.value),
            _ci(s, "generalization"),
            format_rank(result, "generalization", name),
            format_percent(result.relative_ranks["generalization"][name]),
            "; ".join(s.flags) if s.flags else "–",
        ]
        rows.append(row)
    head = []
    if result.verdict is not None:
        head = [*result.verdict.text, ""]
    lines = head + [
        "| " + " | ".join(header) + " |",
        "|" + "|".join("---" if i == 0 else "--:" for i in range(len(header))) + "|",
    ]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    o = result.options
    notes = [
        "",
        f"{ORDER_WORDS} Common frame: {result.common_frame}. Specificity and "
        "generalization: lower is better "
        f"({o['distance'].upper()} distance in the model's parameter space, in the images' "
        f"intensity units; M = {o['n_samples']} samples, seed {o['seed']}); overlap: higher "
        "is better. 95% CI: subject-level interval (jackknife over the subjects: would the "
        "score hold for other subjects?). MC s.e.: Monte-Carlo standard error of the "
        "specificity estimate only (it shrinks as M grows). Rank: 1 is best. Rel. rank: "
        "100% for the best score, 0% for the worst, linear between, (worst - x) / "
        f"(worst - best). {TIES_WORDS}",
        "",
        "| Registration | Frame from | Spread mean (mm) | Spread flagged | Spread max (mm) | "
        "Folded (mean) | Folded (worst image) | SDlogJ | det J min | det J max | "
        "Inverse consistency (mm) |",
        "|---|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|",
    ]
    for name in order:
        s = result.scores[name]
        pl = s.plausibility
        notes.append(
            f"| {name} | {s.frame.method} | {format_number(s.frame.spread_mean_mm, 3)} | "
            f"{'yes' if frame_spread_flagged(result, name) else 'no'} | "
            f"{format_number(s.frame.spread_max_mm, 3)} | {pl.folded_fraction:.2%} | "
            f"{pl.folded_max:.2%} | {format_number(pl.sdlogj, 3)} | "
            f"{format_number(pl.jacobian_min, 3)} | {format_number(pl.jacobian_max, 3)} | "
            f"{format_number(pl.inverse_consistency_mm, 3)} |"
        )
    notes += [
        "",
        "Frame spread: how far the per-image estimates of the transform into the common "
        "frame lie from it. " + frame_spread_words(result)[1],
    ]
    return "\n".join(lines + notes + subjects_summary(result)) + "\n"


#: How the reports say what a subject flag, a registration flag and the concern are.
SUBJECT_FLAG_WORDS = (
    "A subject flag sets one subject apart from the rest of its cohort under the same "
    "registration. A registration flag is a kind of flag at least half of a registration's "
    "subjects (and at least two) carry: a property of the registration, not of those "
    "subjects, said once and not counted as theirs. A registration's reference, when it is "
    "one of the subjects (registered to itself), is named as such and not judged."
)
CONCERN_WORDS = (
    "Subjects are listed worst first by their concern: a weighted mean of their robust "
    "z-scores, each signed so that positive is worse (label overlap with the others, weight "
    "3, where labels exist; distance to the others with gain and bias divided out, SDlogJ "
    "and inverse consistency, weight 1 each, the last two only above zero). Above a "
    "threshold (--subject-concern, 1.75 by default; --subject-concern-without-labels where "
    "a subject's labels were not measured) it flags the subject; look at the first "
    "few even when none is flagged. Flags on absolute limits (folding, mirroring, a "
    "duplicate, off the grid) are not in it."
)

#: How many subjects of highest concern summary.md names for a registration that flags none.
WORST_NAMED = 3


def _reference_words(s) -> str:
    """The words " other than its reference" for a registration whose reference is one of
    its subjects; empty otherwise."""
    return " other than its reference" if any(q.reference for q in s.subjects) else ""


def concern_text(concern: float | None) -> str:
    """A concern (robust standard deviations) to one decimal (``"2.4"``); a dash for None."""
    return "–" if concern is None else f"{concern:.1f}"


def _concern_words(q) -> str:
    """A subject's concern in words: ``"concern 2.4 (model distance)"``."""
    if q.concern is None:
        return "no concern measured"
    return f"concern {concern_text(q.concern)} ({q.concern_from})"


def subjects_summary(result) -> list[str]:
    """The lines of ``summary.md`` on the subjects of every registration.

    Per registration (in the verdict's order): its registration flags, each once; its
    reference when that is one of the subjects; its flagged subjects worst first (by
    :attr:`~itk_nrreval.measures.subject_qc.SubjectQC.concern`), each with its manifest index,
    image, concern, diagnosis and subject flags; or, when none is flagged, the
    :data:`WORST_NAMED` subjects of highest concern. Then the subjects left out of every
    score.
    """
    if not any(s.subjects for s in result.scores.values()):
        return []
    lines = [
        "",
        "## Flagged subjects",
        "",
        "Each subject compared with the rest of its cohort under the same registration "
        "(robust z-scores, z = (x - median) / (1.4826 MAD)): its distance to the texture "
        "model of the others, its deformation, its label overlap with the others, its "
        "coverage of the common grid (per-subject values in subjects.csv, every subject "
        f"ranked). {SUBJECT_FLAG_WORDS} {CONCERN_WORDS}",
        "",
    ]
    left_out = result.options.get("left_out_of_scores") or []
    if left_out:
        first = next(iter(result.scores.values()))
        names = ", ".join(f"{i} ({first.subjects[i].image})" for i in left_out)
        lines += [
            f"Left out of every registration's scores (off the common grid): subject {names}.",
            "",
        ]
    order = list(result.verdict.ranking) if result.verdict is not None else list(result.scores)
    for name in order:  # the order of the table above: the verdict's
        s = result.scores[name]
        if not s.subjects:
            continue
        flagged = ranked([q for q in s.subjects if q.flags])
        judged = [q for q in s.subjects if not q.reference]
        of = f"of the {len(judged)} subjects{_reference_words(s)}"
        if flagged:
            lines.append(f"- {name}: {len(flagged)} {of} flagged:")
        else:
            worst = [q for q in ranked(judged) if q.concern is not None][:WORST_NAMED]
            named = ", ".join(f"subject {q.index} ({q.image}), {_concern_words(q)}" for q in worst)
            lines.append(
                f"- {name}: none {of} is flagged"
                + (f"; the highest concern: {named}." if named else ".")
            )
        for flag in registration_flags(s.subjects):
            lines.append(f"  - registration flag: {flag}.")
        for q in s.subjects:
            if q.reference:
                lines.append(
                    f"  - subject {q.index} ({q.image}): the reference of this registration "
                    "(registered to itself): not judged."
                )
        for q in flagged:
            cause = q.diagnosis if q.diagnosis is not None else "no common cause recognised"
            lines.append(
                f"  - subject {q.index} ({q.image}), {_concern_words(q)}: {cause}. "
                f"Subject flags: {'; '.join(q.flags)}."
            )
    return lines


def _missing(v) -> bool:
    return v is None or (isinstance(v, float) and math.isnan(v))


#: The columns of ``subjects.csv`` taken from a subject's deformation, in order.
_SUBJECT_DEFORMATION = (
    "folded_fraction",
    "sdlogj",
    "sdlogj_z",
    "jacobian_min",
    "jacobian_max",
    "inverse_consistency_mm",
    "inverse_consistency_z",
    "linear_det",
    "nonlinear_rms_mm",
    "nonlinear_rms_z",
    "displacement_rms_mm",
    "frame_deviation_mm",
    "frame_deviation_z",
)


def subjects_csv(result) -> str:
    """One row per registration and subject: the subject's quality control, worst first.

    Within each registration the subjects are ranked worst first by their concern
    (:func:`itk_nrreval.measures.subject_qc.ranked`; ``rank`` 1 is the worst; the reference last).
    Columns: registration, rank, index (manifest), image, reference (the registration's
    reference: not judged), concern and concern_from (the term that contributes most to
    it), in_scores,
    score (distance to the model of the others, intensity units), z, corrected_distance (distance of
    its bias-corrected image to the others' mean) and corrected_z, overlap, overlap_z,
    coverage, brain_mask_dice (with brain masks), the deformation measures (mm where a
    length) and their z, flags (the subject's own, joined by "; "), registration_flags (the
    registration's flags it shares, joined by "; "), diagnosis. Empty cells: not computed.
    """
    fields = ["registration", "rank", "index", "image", "reference", "concern", "concern_from"]
    fields += [
        "in_scores",
        "score",
        "z",
        "corrected_distance",
        "corrected_z",
        "overlap",
        "overlap_z",
    ]
    fields += ["coverage", "brain_mask_dice"]
    fields += [*_SUBJECT_DEFORMATION, "flags", "registration_flags", "diagnosis"]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    w.writeheader()
    for name, s in result.scores.items():
        for rank, q in enumerate(ranked(s.subjects), start=1):
            row = {
                "registration": name,
                "rank": rank,
                "index": q.index,
                "image": q.image,
                "reference": q.reference,
                "concern": q.concern,
                "concern_from": q.concern_from or "",
                "in_scores": q.in_scores,
                "score": q.score,
                "z": q.z,
                "corrected_distance": q.corrected_distance,
                "corrected_z": q.corrected_z,
                "overlap": q.overlap,
                "overlap_z": q.overlap_z,
                "coverage": q.coverage,
                "brain_mask_dice": q.brain_mask_dice,
                **{k: q.deformation.get(k) for k in _SUBJECT_DEFORMATION},
                "flags": "; ".join(q.flags),
                "registration_flags": "; ".join(q.registration_flags),
                "diagnosis": q.diagnosis or "",
            }
            w.writerow({k: "" if _missing(v) else v for k, v in row.items()})
    return buf.getvalue()


def results_csv(result) -> str:
    """One row per registration: scores, standard errors, ranks, relative ranks, frame."""
    fields = ["registration", "specificity", "specificity_stderr"]
    fields += ["specificity_ci95_lo", "specificity_ci95_hi"]
    fields += ["generalization", "generalization_stderr"]
    fields += ["generalization_ci95_lo", "generalization_ci95_hi"]
    overlaps = [m for m in result.measures if m.startswith("overlap.")]
    fields += overlaps
    fields += [f"{m}_ci95_{e}" for m in overlaps for e in ("lo", "hi")]
    fields += [f"rank.{m}" for m in result.measures]
    fields += [f"relative_rank.{m}" for m in result.measures]
    fields += [f"tied_with.{m}" for m in result.measures]
    fields += ["frame_method", "frame_spread_mean_mm", "frame_spread_max_mm"]
    fields += ["folded_fraction", "folded_max", "sdlogj", "jacobian_min", "jacobian_max"]
    fields += ["inverse_consistency_mm", "flags"]
    # only where computed: a result without it writes the columns it always wrote
    with_dl = any(s.description_length is not None for s in result.scores.values())
    fields += ["description_length_bits", "family"] if with_dl else []
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    w.writeheader()
    for name, s in result.scores.items():
        row = {
            "registration": name,
            "specificity": s.specificity.value,
            "specificity_stderr": s.specificity.stderr,
            "generalization": s.generalization.value,
            "generalization_stderr": s.generalization.stderr,
            "frame_method": s.frame.method,
            "frame_spread_mean_mm": s.frame.spread_mean_mm,
            "frame_spread_max_mm": s.frame.spread_max_mm,
            "folded_fraction": s.folded_fraction,
            "folded_max": s.folded_max,
            "sdlogj": s.plausibility.sdlogj,
            "jacobian_min": s.plausibility.jacobian_min,
            "jacobian_max": s.plausibility.jacobian_max,
            "inverse_consistency_mm": s.plausibility.inverse_consistency_mm,
            "flags": "; ".join(s.flags),
        }
        if with_dl:
            dl = s.description_length
            row["description_length_bits"] = None if dl is None else dl.bits
            row["family"] = None if s.family is None else " ".join(s.family)
        for m in ["specificity", "generalization", *overlaps]:
            iv = s.intervals.get(m)
            row[f"{m}_ci95_lo"] = iv.lo if iv is not None else None
            row[f"{m}_ci95_hi"] = iv.hi if iv is not None else None
        row.update({m: s.measures()[m] for m in overlaps})
        row.update({f"rank.{m}": result.ranks[m][name] for m in result.measures})
        row.update({f"relative_rank.{m}": result.relative_ranks[m][name] for m in result.measures})
        row.update({f"tied_with.{m}": ";".join(result.tied_with(m, name)) for m in result.measures})
        w.writerow(row)
    return buf.getvalue()


#: The deformation's numbers papers report beside Dice and HD95, from each registration's
#: :class:`~itk_nrreval.io.plausibility.Plausibility` (means over its images).
METRICS_DEFORMATION = ("sdlogj", "folded_fraction")


def deformation_metrics(plausibility) -> dict[str, float | None]:
    """The deformation's numbers papers report: SDlogJ and the folded fraction, and the
    non-diffeomorphic fraction and volume where the plausibility has them (its
    ``*diffeomorphic*`` fields but the worst image's, ``*_max``), by name, NaN as None."""
    values = plausibility.to_dict()
    extra = [k for k in values if "diffeomorphic" in k and not k.endswith("_max")]
    names = [*METRICS_DEFORMATION, *extra]
    return {k: values.get(k) for k in names}


def _summary_cells(prefix: str, summary) -> dict:
    return {
        f"{prefix}_mean": summary.mean,
        f"{prefix}_std": summary.std,
        f"{prefix}_worst30": summary.worst30,
    }


def metrics_csv(result) -> str:
    """``metrics.csv``: the numbers registration papers report, one row per registration
    (``label`` "all") and one per registration and label after it.

    Columns: registration, label, against ("reference": each subject against the
    registration's reference subject; "pairs": every pair of subjects), reference (its
    manifest index), cases (how many compared), dice_mean / _std / _worst30 and
    hd95_mm_mean / _std / _worst30 (mm; ``worst30``: the mean of the 30% worst cases, the
    lowest Dice and the largest HD95; "all": each case's mean over its labels first), then
    on the registration's row SDlogJ, the folded fraction and any non-diffeomorphic fraction
    (:func:`deformation_metrics`; means over its images). Empty cells: not computed (no
    labels, or a label row's deformation columns). With the manifest's ``label_names``, a
    ``label_name`` column follows ``label``.
    """
    deformation: list[str] = []
    for s in result.scores.values():
        deformation += [k for k in deformation_metrics(s.plausibility) if k not in deformation]
    named = any(
        s.label_metrics is not None and s.label_metrics.names for s in result.scores.values()
    )
    fields = ["registration", "label", *(["label_name"] if named else []), "against"]
    fields += ["reference", "cases"]
    fields += [f"{m}_{a}" for m in ("dice", "hd95_mm") for a in ("mean", "std", "worst30")]
    fields += deformation
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    w.writeheader()
    for name, s in result.scores.items():
        lm = s.label_metrics
        row = {"registration": name, "label": "all", **deformation_metrics(s.plausibility)}
        if lm is not None:
            dice, hd = lm.overall()
            row.update(against=lm.against, reference=lm.reference, cases=len(lm.cases))
            row.update(_summary_cells("dice", dice), **_summary_cells("hd95_mm", hd))
        w.writerow({k: "" if _missing(v) else v for k, v in row.items()})
        if lm is None:
            continue
        for value, (dice, hd) in lm.per_label().items():
            row = {"registration": name, "label": value, "against": lm.against}
            if named:
                row["label_name"] = (lm.names or {}).get(value, "")
            row.update(reference=lm.reference, cases=dice.n_cases)
            row.update(_summary_cells("dice", dice), **_summary_cells("hd95_mm", hd))
            w.writerow({k: "" if _missing(v) else v for k, v in row.items()})
    return buf.getvalue()


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serializable: {type(o).__name__}")


def results_json(result) -> str:
    """The text of ``results.json``: :meth:`EvaluationResult.to_dict
    <itk_nrreval.evaluation.EvaluationResult.to_dict>`, indented, numpy values as Python's."""
    return json.dumps(result.to_dict(), indent=2, default=_json_default) + "\n"
