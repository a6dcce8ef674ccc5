"""The end-to-end demo: the paper's Section V comparison on generated brain-like data.

A population with known true correspondence (:mod:`data_synth`) is registered by the five
algorithms of the paper -- fluid, groupwise, pairwise to a near-mean and to a far-from-mean
reference, and affine -- with real engines (:mod:`itk_nrreval.experiments.registration`); the
results are brought into the fluid registration's frame and scored by specificity and by the
generalized overlap (:func:`itk_nrreval.evaluate`). Because the data are generated, the true mean
correspondence error of each registration is known too, and is reported beside them.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import SimpleITK as sitk
from scipy import stats

from .._output import (
    atomic_path,
    check_output_folder,
    claim_output_folder,
    write_json,
    write_text,
)
from ..evaluation import EvaluationResult, evaluate, higher_is_better, ranks, relative_ranks
from ..io._images import read_image
from ..io.manifest import Manifest, add_registration, load_manifest, write_manifest
from .correspondence import correspondence_error

__all__ = ["DEMO_REGISTRATIONS", "DemoResult", "run_demo", "DEMO_OUTPUTS"]

#: (name, method, reference choice), in the order of the paper's Table 3.
DEMO_REGISTRATIONS = (
    ("fluid", "fluid", "near-mean"),
    ("groupwise", "groupwise", None),
    ("pairwise_near", "pairwise", "near-mean"),
    ("pairwise_far", "pairwise", "far-from-mean"),
    ("affine", "affine", "near-mean"),
)
_TABLE_OVERLAPS = ("inverse_volume", "inverse_volume_complexity")


@dataclass(frozen=True)
class DemoResult:
    """What the demo measured.

    Attributes
    ----------
    evaluation : EvaluationResult
        Specificity, generalization and overlaps of the five registrations (fluid frame).
    correspondence_error_mm : dict of str to float
        True mean correspondence error per registration (mm; lower is better): see
        :func:`itk_nrreval.experiments.correspondence.correspondence_error`.
    agreement : dict of str to float
        Spearman rank correlation, over the five registrations, between the specificity
        ranking and each other measure's ranking (+1: the same order).
    seconds : dict of str to float
        Wall time of each stage.
    table : str
        The Markdown table (paper's Table 3 layout plus the true correspondence error).
    out : Path
        Where everything was written.
    """

    evaluation: EvaluationResult
    correspondence_error_mm: dict[str, float]
    agreement: dict[str, float]
    seconds: dict[str, float]
    table: str
    out: Path


def _table(evaluation: EvaluationResult, error: dict[str, float]) -> str:
    from ..report import format_number, format_percent, format_rank

    # the verdict's order, as summary.md and report.html list them: one order everywhere
    names = list(evaluation.verdict.ranking) if evaluation.verdict else list(evaluation.scores)
    err_rank = ranks(error, higher_is_better=False)
    err_rel = relative_ranks(error, higher_is_better=False)
    header = ["Registration"]
    for w in _TABLE_OVERLAPS:
        header += [f"Overlap ({w.replace('_', ' ')})", "Rank", "Rel."]
    header += ["Specificity", "95% CI (subjects)", "MC s.e.", "Rank", "Rel."]
    header += ["True corr. error (mm)", "Rank", "Rel."]
    lines = ["| " + " | ".join(header) + " |", "|---" + "|--:" * (len(header) - 1) + "|"]
    for name in names:
        s = evaluation.scores[name]
        row = [name]
        for w in _TABLE_OVERLAPS:
            m = f"overlap.{w}"
            row += [
                format_number(s.overlap[w], 3),
                format_rank(evaluation, m, name),
                format_percent(evaluation.relative_ranks[m][name]),
            ]
        iv = s.intervals.get("specificity")
        ci = "–" if iv is None else f"[{format_number(iv.lo, 4)}, {format_number(iv.hi, 4)}]"
        row += [
            format_number(s.specificity.value, 4),
            ci,
            format_number(s.specificity.stderr, 2),
            format_rank(evaluation, "specificity", name),
            format_percent(evaluation.relative_ranks["specificity"][name]),
        ]
        row += [format_number(error[name], 3), str(err_rank[name]), format_percent(err_rel[name])]
        if s.flags:
            row[0] += " (flagged)"
        lines.append("| " + " | ".join(row) + " |")
    text = list(evaluation.verdict.text) if evaluation.verdict is not None else []
    return "\n".join([*text, "", *lines]) + "\n"


def _agreement(evaluation: EvaluationResult, error: dict[str, float]) -> dict[str, float]:
    names = list(evaluation.scores)
    # the order of the scores themselves: the reports' ranks tie scores within noise
    by_score = {
        m: ranks(
            {n: evaluation.scores[n].measures()[m] for n in names},
            higher_is_better=higher_is_better(m),
        )
        for m in evaluation.ranks
    }
    spec = [by_score["specificity"][n] for n in names]
    others = {m: r for m, r in by_score.items() if m != "specificity"}
    others["true_correspondence_error"] = ranks(error, higher_is_better=False)
    return {m: float(stats.spearmanr(spec, [r[n] for n in names])[0]) for m, r in others.items()}


DEMO_OUTPUTS = (
    "data",
    "manifest.yaml",
    "registrations",
    "brain_mask.nii.gz",
    "evaluation",
    "demo_table.md",
    "demo.json",
)
"""What :func:`run_demo` writes into its folder (and may replace on a rerun)."""


def run_demo(
    *,
    out: str | os.PathLike = "demo-output",
    kind: str = "phantom",
    dim: int = 2,
    n: int = 36,
    n_samples: int = 500_000,
    seed: int = 0,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
) -> DemoResult:
    """Generate a population, register it five ways, evaluate, and write everything to `out`.

    Parameters
    ----------
    out : path
        Output folder: ``data/`` (the population, its true transforms and ``manifest.yaml``
        with the registration ``truth``), ``registrations/<name>/`` (transforms ``.h5``,
        reference, settings log), ``manifest.yaml`` (the five registrations, fluid first, so
        the fluid frame is common), ``brain_mask.nii.gz`` (the fluid reference's brain,
        dilated by 3 voxels: specificity and the correspondence error are measured inside
        it), ``evaluation/`` (``results.json``, ``results.csv``, ``summary.md``, figures and
        ``report.html``), ``demo_table.md`` and ``demo.json``.
    kind : {"phantom", "mni"}
        The population's source (:func:`data_synth.make_population`).
    dim : {2, 3}
    n : int
        Number of images (the paper: 36).
    n_samples : int
        Specificity samples M (the paper: 500,000), L1 distance, seeded.
    seed : int
        Seeds the population, the registrations' metric sampling and the specificity.
    progress : bool
        Progress bars on stderr.
    log : callable, optional
        Receives one line per stage (default: print to stderr).
    """
    from data_synth import make_population, write_population

    say = log or (lambda line: print(line, file=sys.stderr, flush=True))
    out = claim_output_folder(
        check_output_folder(out, option="out", command="demo"),
        entries=DEMO_OUTPUTS,
        command="demo",
    )
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    say(f"[demo] generating {n} {kind} subjects ({dim}D)")
    pop = make_population(kind, dim=dim, n=n, seed=seed)
    truth_manifest = write_population(pop, out / "data", progress=progress)
    truth = load_manifest(truth_manifest)
    seconds["generate"] = time.perf_counter() - t0

    manifest = out / "manifest.yaml"
    with contextlib.suppress(FileNotFoundError):
        manifest.unlink()  # a fresh comparison: registrations of an earlier run do not mix in
    stems = [Path(p).name.split(".")[0] for p in truth.images]
    images = list(truth.images)
    results = _register_five(images, seed=seed, progress=progress, say=say, seconds=seconds)
    for name, _, _ in DEMO_REGISTRATIONS:  # fluid first: its frame is the common one
        files = results[name].write(out / "registrations" / name, names=stems)
        add_registration(
            manifest,
            name,
            reference=files["reference"],
            transforms=files["transforms"],
            reference_index=results[name].reference_index,
            images=images,
            labels=list(truth.labels),
            # method and engine: the verdict compares roughness only within one family
            parameters=results[name].manifest_parameters(),
        )

    m, mask = _brain_mask(out, manifest, dim)

    say(f"[demo] evaluating in the fluid frame (M = {n_samples:,} samples, L1)")
    t = time.perf_counter()
    evaluation = evaluate(manifest, n_samples=n_samples, seed=seed, progress=progress)
    evaluation.write(out / "evaluation")  # figures, report.html, results.*
    seconds["evaluate"] = time.perf_counter() - t

    t = time.perf_counter()
    error = correspondence_error(
        evaluation, m, [s.subject_to_template for s in pop.subjects], mask=mask
    )
    seconds["correspondence_error"] = time.perf_counter() - t
    seconds["total"] = time.perf_counter() - t0

    table = _table(evaluation, error)
    agreement = _agreement(evaluation, error)
    write_text(out / "demo_table.md", table)
    write_json(
        out / "demo.json",
        {
            "population": {"kind": kind, "dim": dim, "n": n, "seed": seed},
            "n_samples": n_samples,
            "true_correspondence_error_mm": error,
            "spearman_vs_specificity_ranks": agreement,
            "seconds": {stage: round(v, 2) for stage, v in seconds.items()},
            "evaluation": evaluation.to_dict(),
        },
    )
    return DemoResult(evaluation, error, agreement, seconds, table, out)


def _register_five(images, *, seed, progress, say, seconds) -> dict:
    """The paper's five registrations of `images` (:data:`DEMO_REGISTRATIONS`), by name; each
    stage's time added to `seconds`. The elastix methods run in one elastix worker, or on
    SimpleITK where itk-elastix is missing."""
    from .registration import register
    from .registration._elastix_worker import ElastixWorker, elastix_available

    use_elastix = elastix_available()
    results = {}
    with ElastixWorker() if use_elastix else contextlib.nullcontext() as worker:
        # One affine stage per reference, shared by the methods that use that reference.
        affine_stage = {}
        for choice in ("near-mean", "far-from-mean"):
            say(f"[demo] affine alignment to the {choice} reference")
            t = time.perf_counter()
            affine_stage[choice] = register(
                images, method="affine", reference_choice=choice, seed=seed, progress=progress
            )
            seconds[f"affine_{choice}"] = time.perf_counter() - t
        for name, method, choice in DEMO_REGISTRATIONS:
            if method == "affine":
                results[name] = affine_stage[choice]
                continue
            say(f"[demo] registering: {name}")
            t = time.perf_counter()
            uses_elastix = method in ("pairwise", "groupwise")
            engine = None if not uses_elastix or use_elastix else "simpleitk"
            results[name] = register(
                images,
                method=method,
                engine=engine,
                seed=seed,
                progress=progress,
                elastix_worker=worker if uses_elastix else None,
                affine=affine_stage[choice or "near-mean"],
            )
            seconds[f"register_{name}"] = time.perf_counter() - t
    return results


def _brain_mask(out: Path, manifest: Path, dim: int) -> tuple[Manifest, np.ndarray]:
    """Write ``brain_mask.nii.gz`` and make it `manifest`'s mask; the manifest as it was
    before (without the mask), and the mask (bool, numpy order).

    Like the paper's cropped brain slices, evaluate inside the brain (with a margin of 3
    voxels) of the common frame: the fluid reference is a training image, whose labels say
    where that is."""
    m = load_manifest(manifest)
    k = m.registrations[m.common_frame].reference_index
    brain = sitk.BinaryDilate(
        sitk.Cast(read_image(m.labels[k], what="label map") > 0, sitk.sitkUInt8), [3] * dim
    )
    with atomic_path(out / "brain_mask.nii.gz") as tmp:
        sitk.WriteImage(brain, str(tmp))
    write_manifest(dataclasses.replace(m, mask=(out / "brain_mask.nii.gz").absolute()), manifest)
    return m, sitk.GetArrayFromImage(brain) > 0
