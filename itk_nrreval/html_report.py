"""``report.html``: one self-contained page that reads an evaluation, as MRIQC and fMRIPrep
reports are read.

The page opens from disk with no network and no JavaScript: every figure is a PNG embedded as
a ``data:`` URI, the style sheet is inline, and the only links are to the page's own
sections. It gives, in order: the verdict in words; the scores with their legend, units and
intervals; the summary figures (the same PNG bytes as the files beside it); deformation
plausibility and coverage; the frame-estimate spread; per registration its mean image, a
checkerboard of two subjects, the label contours of one subject with a colour legend, a
log-Jacobian-determinant map and the histogram of log det J over all subjects; the inputs
and the options.

It stays light whatever the number of images N: every picture is a middle slice shrunk to at
most 256 pixels a side (:attr:`EvaluationResult.thumbnails
<itk_nrreval.evaluation.EvaluationResult.thumbnails>`, gathered by the pipeline), and there
is a constant number of pictures per registration; only the list of input files grows
with N.

:meth:`EvaluationResult.write <itk_nrreval.evaluation.EvaluationResult.write>` writes it
through :func:`itk_nrreval.reports.write_reports`; this module takes the result without
importing its class (that import would be a cycle).
"""

from __future__ import annotations

import base64
import html
import math
import re
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from .reports import (
    draw_label_contours,
    figure_pngs,
    format_number,
    format_percent,
    middle_slice,
    png_bytes,
    specificity_units,
    thumbnail,
)

__all__ = ["report_html"]

_DPI = 90  # pixels per inch of the per-registration figures

_WEIGHTING_WORDS = {
    "volume": "label weight 1: every voxel counts the same, so large labels dominate",
    "inverse_volume": "label weight 1 / volume: every label counts the same, whatever its size",
    "inverse_volume_squared": "label weight 1 / volume²: small labels count most",
    "complexity": "label weight = boundary complexity: intricate labels count more",
    "inverse_volume_complexity": "label weight = complexity / volume",
}

_FRAME_WORDS = {
    "common": "this is the common frame",
    "frame_transform": "the frame transform given in the manifest",
    "reference_index": "its reference is one of the images (the common registration's "
    "transform of that image)",
    "mean": "the mean of the per-image estimates (a displacement field)",
}

_CSS = """
body{font-family:-apple-system,'Segoe UI',Helvetica,Arial,sans-serif;margin:0;color:#222;
background:#fafafa;line-height:1.45}
main{max-width:1180px;margin:0 auto;padding:0 24px 48px}
header{background:#2c3e50;color:#fff;padding:18px 24px}
header h1{margin:0;font-size:1.6em}header p{margin:4px 0 0;color:#d5dde5}
h2{border-bottom:2px solid #2c3e50;padding-bottom:4px;margin-top:36px}
h3{margin-bottom:4px}
nav ol{columns:2;margin:0}nav a,a.top{color:#1f5f99;text-decoration:none}
nav a:hover{text-decoration:underline}
a.top{font-size:.85em;float:right;font-weight:normal}
.verdict{background:#eaf4ea;border-left:6px solid #2e7d32;padding:10px 16px;font-size:1.1em}
.verdict.flagged{background:#fdf0e6;border-left-color:#d9822b}
table{border-collapse:collapse;margin:8px 0 12px;font-size:.9em;background:#fff}
th,td{border:1px solid #ccd;padding:3px 7px;text-align:right;vertical-align:top}
th{background:#e8edf2}td:first-child,th:first-child{text-align:left}
td{white-space:nowrap}td.text{text-align:left;max-width:420px;white-space:normal}
tr.flagged td{background:#fff4ec}
dl.legend{font-size:.88em;background:#fff;border:1px solid #dde;padding:8px 14px;
columns:2;column-gap:28px}
dl.legend dt,dl.legend dd{break-inside:avoid}dl.legend dt{break-after:avoid}
dl.legend dt{font-weight:bold;margin-top:6px}dl.legend dd{margin-left:18px}
figure{margin:12px 12px 12px 0;background:#fff;border:1px solid #dde;padding:8px;
display:inline-table;vertical-align:top}
figure img{max-width:100%;height:auto;display:block}
figure.half img{max-width:520px}
figcaption{font-size:.86em;color:#444;display:table-caption;caption-side:bottom;
background:#fff;border:1px solid #dde;border-top:0;padding:4px 8px 8px}
.flag{color:#b34700;font-weight:bold}
.ci{color:#555;font-size:.85em;white-space:nowrap}
div.wide{overflow-x:auto}
code{background:#eef;padding:0 3px}
details{margin:6px 0}
footer{font-size:.8em;color:#666;margin-top:40px}
"""


def _e(text) -> str:
    return html.escape(str(text), quote=True)


def _img(png: bytes, alt: str) -> str:
    data = base64.b64encode(png).decode("ascii")
    return f'<img src="data:image/png;base64,{data}" alt="{_e(alt)}">'


def _figure(png: bytes, alt: str, caption: str, *, css: str = "") -> str:
    cls = f' class="{css}"' if css else ""
    return f"<figure{cls}>{_img(png, alt)}<figcaption>{caption}</figcaption></figure>"


def _slugs(names: Sequence[str]) -> dict[str, str]:
    """An id per registration: ``reg-`` and its name's letters, digits, ``-`` and ``_``."""
    out: dict[str, str] = {}
    used: set[str] = set()
    for name in names:
        base = "reg-" + (re.sub(r"[^A-Za-z0-9_-]+", "-", name).strip("-") or "x")
        slug, k = base, 2
        while slug in used:
            slug, k = f"{base}-{k}", k + 1
        used.add(slug)
        out[name] = slug
    return out


def _subject(result, i: int) -> str:
    """How subject i is named: its image file's name, or its index for objects in memory."""
    images = result.inputs.get("images") or []
    if i < len(images) and isinstance(images[i], str):
        return f"subject {i} ({Path(images[i]).name})"
    return f"subject {i}"


def _ci(iv) -> str:
    if iv is None or not math.isfinite(iv.lo) or not math.isfinite(iv.hi):
        return "–"
    return f"[{format_number(iv.lo)}, {format_number(iv.hi)}]"


def _rel(result, measure: str, name: str) -> str:
    rank = result.ranks[measure][name]
    rel = result.relative_ranks[measure][name]
    return f"{format_percent(rel)} ({rank if rank is not None else '–'})"


# ----------------------------------------------------------------------------- figures


def _grey_limits(*arrays: np.ndarray) -> tuple[float, float]:
    vals = np.concatenate([np.asarray(a, float).ravel() for a in arrays])
    vals = vals[np.isfinite(vals)]
    if not vals.size:
        return 0.0, 1.0
    lo, hi = np.percentile(vals, [0.5, 99.5])
    return (float(lo), float(hi)) if hi > lo else (float(lo), float(lo) + 1.0)


def _aspect(spacing) -> float:
    return 1.0 if spacing is None else float(spacing[0] / spacing[1])


def _checkerboard(a: np.ndarray, b: np.ndarray, tiles: int = 8) -> np.ndarray:
    """`a` on the even tiles, `b` on the odd ones; `tiles` tiles along the longer side."""
    size = max(1, round(max(a.shape) / tiles))
    r, c = np.indices(a.shape)
    return np.where((r // size + c // size) % 2 == 0, a, b)


def _images_figure(result, name: str) -> bytes:
    """Mean image, checkerboard of subjects 0 and 1, subject 0 with its label contours."""
    from matplotlib.figure import Figure

    t = result.thumbnails.get(name, {})
    mean = thumbnail(middle_slice(result.mean_images[name]))
    aspect = _aspect(t.get("common_spacing"))
    panels = [("mean", mean)]
    if "image_0" in t and "image_1" in t:
        panels.append(("checker", _checkerboard(thumbnail(t["image_0"]), thumbnail(t["image_1"]))))
    if "image_0" in t:
        panels.append(("subject", thumbnail(t["image_0"])))
    legend = "labels_0" in t
    fig = Figure(figsize=(2.7 * len(panels) + (0.9 if legend else 0.0), 3.0))
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    lo, hi = _grey_limits(*[p for _, p in panels])
    titles = {
        "mean": f"mean of the {result.scores[name].specificity.n_images} images",
        "checker": "checkerboard: subjects 0 | 1",
        "subject": "subject 0" + (" and its labels" if legend else ""),
    }
    for ax, (kind, arr) in zip(axes, panels, strict=True):
        ax.imshow(arr, cmap="gray", vmin=lo, vmax=hi, origin="lower", aspect=aspect)
        if kind == "subject" and legend:
            draw_label_contours(ax, thumbnail(t["labels_0"], mode="nearest"), aspect=aspect)
        ax.set_title(titles[kind], fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.subplots_adjust(wspace=0.05)
    return png_bytes(fig, dpi=_DPI)


def _jacobian_figure(result, name: str) -> bytes | None:
    """log det J of subject 0 (map, colour bar, folded voxels) and the histogram of all."""
    from matplotlib import colormaps
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    t = result.thumbnails.get(name, {})
    if "detj_0" not in t or "log_jacobian_counts" not in t:
        return None
    det = np.asarray(t["detj_0"], float)
    folded = thumbnail(det <= 0, mode="any")
    with np.errstate(divide="ignore", invalid="ignore"):
        logj = thumbnail(np.where(det > 0, np.log(np.where(det > 0, det, 1.0)), np.nan))
    finite = np.abs(logj[np.isfinite(logj)])
    limit = float(np.clip(np.percentile(finite, 99) if finite.size else 0.1, 0.1, 2.0))
    fig = Figure(figsize=(7.6, 3.0), layout="constrained")
    ax, hx = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.0, 1.35]})
    # 32 colours: a map read against its colour bar (and a PNG with a palette)
    cmap = colormaps["RdBu_r"].resampled(32).with_extremes(bad=(0.85, 0.85, 0.85))
    aspect = _aspect(t.get("reference_spacing"))
    im = ax.imshow(
        logj,
        cmap=cmap,
        vmin=-limit,
        vmax=limit,
        origin="lower",
        aspect=aspect,
        interpolation="nearest",
    )
    if folded.any():
        overlay = np.zeros((*folded.shape, 4))
        overlay[folded] = (0.0, 0.0, 0.0, 1.0)
        ax.imshow(overlay, origin="lower", aspect=aspect, interpolation="nearest")
        ax.legend(
            handles=[Patch(color="black", label="det J <= 0 (folds)")],
            fontsize=6,
            loc="lower left",
            bbox_to_anchor=(0.0, -0.16),
            borderaxespad=0.0,
        )
    cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03, extend="both")
    cb.set_label("log det J  (<0 shrinks, >0 grows)", fontsize=7)
    cb.ax.tick_params(labelsize=7)
    ax.set_title("log det J, subject 0 (reference grid)", fontsize=8)
    ax.set_xticks([])
    ax.set_yticks([])

    counts = np.asarray(t["log_jacobian_counts"], float)
    edges = np.asarray(t["log_jacobian_edges"], float)
    below, above, n_folded = (int(v) for v in t["log_jacobian_outside"])
    total = counts.sum() + below + above + n_folded
    hx.stairs(counts / total if total else counts, edges, fill=True, color="tab:blue")
    hx.axvline(0.0, color="k", lw=0.8, ls="--")
    hx.set_yscale("log")
    bottom, top = hx.get_ylim()
    hx.set_ylim(bottom, top * 30)  # room for the note above the bars
    hx.set_xlim(edges[0], edges[-1])
    hx.set_xlabel("log det J", fontsize=8)
    hx.set_ylabel("fraction of voxels (log scale)", fontsize=8)
    hx.tick_params(labelsize=7)
    n = result.scores[name].specificity.n_images
    hx.set_title(f"log det J of all {n} subjects ({total:,.0f} voxels)", fontsize=8)
    share = (lambda k: f"{k / total:.2%}") if total else (lambda k: "–")
    hx.text(
        0.02,
        0.97,
        f"below {edges[0]:g}: {share(below)}\nabove {edges[-1]:g}: {share(above)}\n"
        f"folded (det J <= 0): {share(n_folded)}",
        transform=hx.transAxes,
        va="top",
        fontsize=7,
        bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none"},
    )
    return png_bytes(fig, dpi=_DPI)


# ----------------------------------------------------------------------------- sections


def _value_ci(value: float, iv) -> str:
    """A score over its subject-level 95% interval (small, below)."""
    return f'{format_number(value)}<br><span class="ci">{_ci(iv)}</span>'


def _scores_table(result, names: Sequence[str], slugs: Mapping[str, str]) -> str:
    overlaps = [
        m
        for m in ("overlap.inverse_volume", "overlap.inverse_volume_complexity")
        if m in result.ranks
    ]
    head = ["Registration", "Specificity<br>[95% CI]", "MC s.e.", "Rel. (rank)"]
    head += ["Generalization<br>[95% CI]", "s.e.", "Rel. (rank)"]
    for m in overlaps:
        weighting = _e(m.split(".", 1)[1].replace("_", " "))
        head += [f"Overlap, {weighting}<br>[95% CI]", "Rel. (rank)"]
    head += ["Coverage", "Flags"]
    rows = []
    for n in names:
        s = result.scores[n]
        cells = [f'<a href="#{slugs[n]}">{_e(n)}</a>']
        cells += [
            _value_ci(s.specificity.value, s.intervals.get("specificity")),
            format_number(s.specificity.stderr, 2),
            _rel(result, "specificity", n),
            _value_ci(s.generalization.value, s.intervals.get("generalization")),
            format_number(s.generalization.stderr, 2),
            _rel(result, "generalization", n),
        ]
        for m in overlaps:
            cells += [_value_ci(s.measures()[m], s.intervals.get(m)), _rel(result, m, n)]
        cov = s.coverage.fraction if s.coverage is not None else None
        cells.append("–" if cov is None else f"{cov:.1%}")
        cells.append(
            f'<a class="flag" href="#plausibility">{len(s.flags)} flag'
            f"{'s' if len(s.flags) > 1 else ''}</a>"
            if s.flags
            else "none"
        )
        rows.append((n, cells))
    out = ['<div class="wide"><table><thead><tr>']
    out.append("".join(f"<th>{h}</th>" for h in head) + "</tr></thead><tbody>")
    for n, cells in rows:
        cls = ' class="flagged"' if result.scores[n].flags else ""
        tds = "".join(
            f'<td class="text">{c}</td>' if k in (0, len(cells) - 1) else f"<td>{c}</td>"
            for k, c in enumerate(cells)
        )
        out.append(f"<tr{cls}>{tds}</tr>")
    out.append("</tbody></table></div>")
    return "\n".join(out)


def _legend(result) -> str:
    o = result.options
    first = next(iter(result.scores.values()))
    n = first.specificity.n_images
    units = specificity_units(result)
    cov = first.coverage
    evaluated = f"{cov.evaluated:.1%}" if cov is not None else "all"
    groups = o.get("resamples")
    jack = (
        f"a grouped jackknife over the subjects ({groups} groups of the N = {n} subjects)"
        if groups
        else "a jackknife over the subjects"
    )
    items = [
        (
            "Specificity",
            "how close images drawn at random from the registration's texture model (a "
            "Gaussian model of the N images resampled into the common frame) come to the "
            f"nearest real image: the mean distance in the model's parameter space ({units}"
            f"; M = {o['n_samples']:,} samples, seed {o['seed']}). <b>Lower is better</b>: a "
            "good registration's model only makes realistic images.",
        ),
        (
            "95% CI",
            f"the subject-level 95% interval, from {jack}: would the score hold for other "
            "subjects? Compare registrations with it (and with the pairwise differences "
            "further down). A dash: not computed (confidence off, or fewer than 4 subjects).",
        ),
        (
            "MC s.e.",
            "Monte-Carlo standard error of the specificity estimate only: the error from "
            "drawing a finite number M of model samples. It shrinks as M grows and says "
            "nothing about other subjects.",
        ),
        (
            "Generalization",
            "the converse: how close each real image comes to the nearest model sample; same "
            "units, <b>lower is better</b>. Its s.e. is the standard deviation over the N "
            "images divided by sqrt(N - 1); its 95% CI is subject-level, as above.",
        ),
        (
            "Overlap",
            "generalized Tanimoto overlap of the label maps resampled into the common frame "
            "(fuzzy memberships, all pairs of images at once), <b>0 to 1, higher is "
            "better</b>, one column per label weighting (every weighting further down). "
            "Even a perfect registration stays below 1: interpolating the labels into the "
            "common frame blurs every boundary over about a voxel.",
        ),
        (
            "Rel. (rank)",
            "the normalised score 100% &times; (worst &minus; x) / (worst &minus; best) among "
            "the registrations compared: 100% for the best, 0% for the worst, linear between; "
            "it is <b>not a rank</b>. The rank (1 = best) is in parentheses.",
        ),
        (
            "Coverage",
            "the fraction of the common grid (inside the mask) where every image has a value "
            "under this registration (its field of view carried through the transforms). The "
            f"scores are taken on the {evaluated} covered by every image under every "
            "registration, the same voxels for all.",
        ),
        (
            "Flags",
            "why the deformation is physically implausible (voxels that fold, a rough "
            "Jacobian, frame estimates that disagree); thresholds under Options. A flagged "
            "registration keeps its scores but is ranked after every unflagged one.",
        ),
    ]
    body = "".join(f"<dt>{k}</dt><dd>{v}</dd>" for k, v in items)
    return f'<dl class="legend">{body}</dl>'


def _overlap_table(result, names: Sequence[str]) -> str:
    ws = [m.split(".", 1)[1] for m in result.measures if m.startswith("overlap.")]
    if not ws:
        return ""
    head = "".join(
        f"<th>{_e(w.replace('_', ' '))}<br>[95% CI]</th><th>Rel. (rank)</th>" for w in ws
    )
    rows = []
    for n in names:
        s = result.scores[n]
        cells = "".join(
            f"<td>{_value_ci(s.overlap[w], s.intervals.get(f'overlap.{w}'))}</td>"
            f"<td>{_rel(result, f'overlap.{w}', n)}</td>"
            for w in ws
        )
        rows.append(f'<tr><td class="text">{_e(n)}</td>{cells}</tr>')
    words = "".join(
        f"<li><b>{_e(w.replace('_', ' '))}</b>: {_e(_WEIGHTING_WORDS.get(w, w))}</li>" for w in ws
    )
    return (
        "<h3>Overlap by label weighting</h3>"
        f'<div class="wide"><table><thead><tr><th>Registration</th>{head}</tr></thead><tbody>'
        + "".join(rows)
        + f"</tbody></table></div><ul>{words}</ul>"
    )


def _comparisons(result) -> str:
    comps = list(result.comparisons)
    if not comps:
        return "<p>No pairwise differences: confidence was not computed.</p>"
    rows = "".join(
        f"<tr><td class='text'>{_e(c.measure)}</td><td class='text'>{_e(c.a)} &minus; "
        f"{_e(c.b)}</td><td>{format_number(c.difference)}</td><td>[{format_number(c.ci95[0])}"
        f", {format_number(c.ci95[1])}]</td><td>{'yes' if c.separable else 'no'}</td></tr>"
        for c in comps
    )
    return (
        "<details><summary>Pairwise differences with their subject-level 95% intervals "
        f"({len(comps)})</summary><table><thead><tr><th>Measure</th><th>a &minus; b</th>"
        "<th>Difference</th><th>95% CI</th><th>Separable (CI excludes 0)</th></tr></thead>"
        f"<tbody>{rows}</tbody></table></details>"
    )


def _plausibility_table(result, names: Sequence[str]) -> str:
    rows = []
    for n in names:
        s = result.scores[n]
        p = s.plausibility
        ic = p.inverse_consistency_mm
        cov = s.coverage
        cells = [
            f"{p.folded_fraction:.2%}",
            f"{p.folded_max:.2%}",
            format_number(p.sdlogj, 3),
            format_number(p.jacobian_min, 3),
            format_number(p.jacobian_max, 3),
            "–" if ic is None else format_number(ic, 3),
            "–" if cov is None else f"{cov.fraction:.1%}",
            "–" if cov is None or not cov.per_image else f"{min(cov.per_image):.1%}",
        ]
        flags = "; ".join(_e(f) for f in s.flags) if s.flags else "plausible"
        cls = ' class="flagged"' if s.flags else ""
        rows.append(
            f'<tr{cls}><td class="text">{_e(n)}</td>'
            + "".join(f"<td>{c}</td>" for c in cells)
            + f'<td class="text">{flags}</td></tr>'
        )
    th = result.options.get("thresholds", {})
    return (
        "<table><thead><tr><th>Registration</th><th>Folded voxels (mean)</th>"
        "<th>Folded (worst image)</th><th>SDlogJ</th><th>det J min</th><th>det J max</th>"
        "<th>Inverse consistency (mm)</th><th>Coverage, all images</th>"
        "<th>Coverage, least image</th><th>In words</th></tr></thead><tbody>"
        + "".join(rows)
        + "</tbody></table>"
        '<dl class="legend">'
        "<dt>Folded voxels</dt><dd>fraction of the voxels of the registration's reference "
        "grid (inside the mask) where the Jacobian determinant det J &le; 0: the map folds "
        "space there. Mean over the images, and the worst single image. Flagged above "
        f"{th.get('folded_mean', float('nan')):.0%} on average or "
        f"{th.get('folded_max', float('nan')):.0%} in one image.</dd>"
        "<dt>SDlogJ</dt><dd>standard deviation of log det J over the voxels that do not "
        "fold (the roughness of the deformation; 0 for a linear transform), mean over the "
        "images.</dd>"
        "<dt>det J min / max</dt><dd>extreme local volume changes over all images, "
        "unclipped (negative where the map folds).</dd>"
        "<dt>Inverse consistency</dt><dd>mean round-trip error |T<sup>-1</sup>(T(p)) "
        "&minus; p| in mm with a numerical inverse; grows where the map folds.</dd>"
        "<dt>Coverage</dt><dd>fraction of the common grid (inside the mask) covered by "
        "every image under this registration, and by the image that covers least.</dd>"
        "</dl>"
    )


def _frames_table(result, names: Sequence[str]) -> str:
    rows = []
    for n in names:
        f = result.scores[n].frame
        rows.append(
            f'<tr><td class="text">{_e(n)}</td>'
            f'<td class="text">{_e(_FRAME_WORDS.get(f.method, f.method))}</td>'
            f"<td>{format_number(f.spread_mean_mm, 3)}</td>"
            f"<td>{format_number(f.spread_max_mm, 3)}</td></tr>"
        )
    return (
        "<table><thead><tr><th>Registration</th><th>Brought into the common frame by</th>"
        "<th>Spread, mean (mm)</th><th>Spread, max (mm)</th></tr></thead><tbody>"
        + "".join(rows)
        + "</tbody></table><p>Each registration has its own reference frame and is brought "
        f"into the common frame (<b>{_e(result.common_frame)}</b>'s) by a transform F. Each "
        "image gives its own estimate F<sub>i</sub> of it; the spread is how far those "
        "estimates lie from F (|F<sub>i</sub>(p) &minus; F(p)| over the images and the "
        "voxels of the common grid, inside the mask). A large spread means the images do not "
        "agree where the registration's frame sits, and comparing it in the common frame is "
        "doubtful.</p>"
    )


def _registration_section(result, name: str, slug: str) -> str:
    s = result.scores[name]
    t = result.thumbnails.get(name, {})
    parts = [
        f'<section id="{slug}"><h2>Registration: {_e(name)} '
        '<a class="top" href="#contents">contents &uarr;</a></h2>'
    ]
    summary = (
        f"Specificity {format_number(s.specificity.value)} "
        f"{_ci(s.intervals.get('specificity'))}, generalization "
        f"{format_number(s.generalization.value)}"
    )
    if s.overlap:
        w = "inverse_volume" if "inverse_volume" in s.overlap else next(iter(s.overlap))
        summary += f", overlap ({w.replace('_', ' ')}) {format_number(s.overlap[w])}"
    summary += (
        f"; frame: {_e(_FRAME_WORDS.get(s.frame.method, s.frame.method))}, spread "
        f"{format_number(s.frame.spread_mean_mm, 3)} mm on average."
    )
    parts.append(f"<p>{summary}</p>")
    if s.flags:
        parts.append('<p class="flag">Flagged: ' + "; ".join(_e(f) for f in s.flags) + ".</p>")
    dim = result.mean_images[name].ndim
    where = "the middle slice of " if dim == 3 else ""
    if t:
        s0, s1 = _subject(result, 0), _subject(result, 1)
        cap = (
            f"Left: {where}the mean of the N resampled images in the common frame: sharp "
            "where the images agree. Middle: checkerboard of two subjects resampled into the "
            f"common frame ({_e(s0)} on the first tile, {_e(s1)} on the next): when they "
            "are aligned, edges run on across the tile borders. Right: "
            f"{_e(s0)} with the boundaries of its labels, resampled into the common frame "
            "(colour legend: label values). Common grey scale in the images' intensity units."
        )
        if "image_1" not in t:
            cap = f"Left: {where}the mean image. Right: {_e(s0)}."
    else:
        cap = f"{where.capitalize()}the mean of the N resampled images in the common frame."
    parts.append(_figure(_images_figure(result, name), f"{name}: images", cap))
    jac = _jacobian_figure(result, name)
    if jac is not None:
        parts.append(
            _figure(
                jac,
                f"{name}: Jacobian determinant",
                f"Left: log of the Jacobian determinant of {_e(_subject(result, 0))}'s "
                f"transform on {where}the registration's own reference grid (blue: local "
                "shrinking, red: growth, black: folding, grey: outside the mask). Right: "
                "histogram of log det J over every voxel of every subject (inside the mask), "
                "64 bins over [-2, 2]; the share beyond the bins and folded is printed.",
            )
        )
    parts.append("</section>")
    return "\n".join(parts)


def _inputs_section(result) -> str:
    inp = dict(result.inputs)

    def item(v) -> str:
        if v is None:
            return "–"
        if isinstance(v, Mapping):
            return _e(", ".join(f"{k}: {val}" for k, val in v.items()))
        return f"<code>{_e(v)}</code>"

    images = inp.get("images") or []
    labels = inp.get("labels")
    rows = [
        ("Manifest", item(inp.get("manifest"))),
        ("Images (N)", str(inp.get("n_images", len(images)))),
        ("Label maps", "none" if not labels else f"{len(labels)} (one per image)"),
        ("Mask", item(inp.get("mask"))),
        ("Common frame", _e(inp.get("common_frame", result.common_frame))),
    ]
    out = ["<table><tbody>"]
    out += [f'<tr><th>{k}</th><td class="text">{v}</td></tr>' for k, v in rows]
    out.append("</tbody></table>")
    regs = inp.get("registrations") or {}
    if regs:
        out.append(
            "<table><thead><tr><th>Registration</th><th>Reference</th><th>Reference index"
            "</th><th>Frame transform</th><th>Transforms (first image)</th></tr></thead>"
            "<tbody>"
        )
        for name, r in regs.items():
            first = (r.get("transforms") or [[]])[0]
            out.append(
                f'<tr><td class="text">{_e(name)}</td><td class="text">'
                f"{item(r.get('reference'))}</td><td>{_e(r.get('reference_index'))}</td>"
                f'<td class="text">{item(r.get("frame_transform"))}</td><td class="text">'
                + ", ".join(item(x) for x in first)
                + "</td></tr>"
            )
        out.append("</tbody></table>")
    listing = "".join(
        f"<li>{item(p)}" + (f" &mdash; labels {item(labels[i])}" if labels else "") + "</li>"
        for i, p in enumerate(images)
    )
    out.append(
        f"<details><summary>The {len(images)} images (subject i is the i-th)</summary>"
        f"<ol start='0'>{listing}</ol></details>"
    )
    return "\n".join(out)


def _options_section(result) -> str:
    def flat(d: Mapping, prefix: str = "") -> list[tuple[str, object]]:
        out = []
        for k, v in d.items():
            if isinstance(v, Mapping):
                out += flat(v, f"{prefix}{k}.")
            else:
                out.append((f"{prefix}{k}", v))
        return out

    rows = flat(dict(result.options)) + [(f"run.{k}", v) for k, v in dict(result.run).items()]
    rows.append(("version", result.version))
    body = "".join(
        f'<tr><th>{_e(k)}</th><td class="text"><code>{_e(v)}</code></td></tr>' for k, v in rows
    )
    return f"<table><tbody>{body}</tbody></table>"


# ----------------------------------------------------------------------------- the page


def report_html(result, *, figures: Mapping[str, bytes] | None = None) -> str:
    """The text of ``report.html`` for an :class:`~itk_nrreval.evaluation.EvaluationResult`.

    Parameters
    ----------
    result : EvaluationResult
    figures : mapping of str to bytes, optional
        The summary figures already rendered (:func:`itk_nrreval.reports.figure_pngs`), to
        embed the same bytes as the files; rendered here when None.

    Returns
    -------
    str
        One self-contained HTML5 page: figures as ``data:image/png;base64`` URIs, inline
        CSS, no script, no external reference; every link targets a section of the page.
    """
    if figures is None:
        figures = figure_pngs(result)
    names = list(result.verdict.ranking) if result.verdict is not None else list(result.names)
    slugs = _slugs(list(result.scores))
    n_images = next(iter(result.scores.values())).specificity.n_images
    o = result.options

    toc = [
        ("verdict", "Verdict"),
        ("scores", "Scores, with their legend"),
        ("figures", "Summary figures"),
        ("details", "Every overlap weighting and pairwise difference"),
        ("plausibility", "Deformation plausibility and coverage"),
        ("frames", "Frame-estimate spread"),
    ]
    toc += [(slugs[n], f"Registration: {n}") for n in names]
    toc += [("inputs", "Inputs"), ("options", "Options")]
    nav = "".join(f'<li><a href="#{k}">{_e(v)}</a></li>' for k, v in toc)

    flagged = any(result.scores[n].flags for n in names)
    verdict = (
        "".join(f"<p>{_e(line)}</p>" for line in result.verdict.text)
        if result.verdict is not None
        else "<p>No verdict was computed.</p>"
    )
    ranking = " &rarr; ".join(f'<a href="#{slugs[n]}">{_e(n)}</a>' for n in names)

    fig_parts = []
    captions = {
        "specificity.png": (
            "Specificity of each registration (lower is better; "
            f"{_e(specificity_units(result))}; M = {o['n_samples']:,} model samples). "
            + (
                "Bars: subject-level 95% intervals (jackknife over the subjects); the "
                "Monte-Carlo error is smaller still."
                if any(result.scores[n].intervals.get("specificity") for n in names)
                else "Bars: 95% Monte-Carlo intervals only (no subject-level interval); "
                "the title says whether they are smaller than the markers."
            )
            + (" Red: flagged as implausible." if flagged else "")
        ),
        "specificity_vs_overlap.png": (
            "Specificity (lower is better) against the generalized overlap of the labels "
            "(higher is better): registrations that do well sit at the lower right. Bars as "
            "stated in the title."
        ),
        "mean_images.png": (
            "The mean image of each registration in the common frame, on one grey scale"
            + (
                ", with the boundaries of subject 0's labels (colour legend: label values)"
                if any("labels_0" in result.thumbnails.get(n, {}) for n in names)
                else ""
            )
            + ". A sharp mean means the images are well aligned."
        ),
    }
    for fname, png in figures.items():
        css = "" if fname == "mean_images.png" else "half"
        fig_parts.append(_figure(png, fname, captions.get(fname, _e(fname)), css=css))

    header = (
        f"<header><h1>Registration evaluation</h1><p>{len(names)} registrations of N = "
        f"{n_images} images, compared in the frame of <b>{_e(result.common_frame)}</b>; "
        f"itk-nrreval {_e(result.version)}</p></header>"
    )
    body = [
        header,
        "<main>",
        f'<nav id="contents"><h2>Contents</h2><ol>{nav}</ol></nav>',
        '<section id="verdict"><h2>Verdict <a class="top" href="#contents">contents &uarr;'
        "</a></h2>"
        f'<div class="verdict{" flagged" if flagged else ""}">{verdict}</div>'
        f"<p>Ranking (by specificity, flagged last): {ranking}</p></section>",
        '<section id="scores"><h2>Scores <a class="top" href="#contents">contents &uarr;</a>'
        "</h2><p>Rows in the verdict's order. Each registration's name links to its "
        "section.</p>",
        _scores_table(result, names, slugs),
        _legend(result),
        "</section>",
        '<section id="figures"><h2>Summary figures <a class="top" href="#contents">'
        "contents &uarr;</a></h2>",
        *fig_parts,
        "</section>",
        '<section id="details"><h2>Every overlap weighting and every pairwise difference '
        '<a class="top" href="#contents">contents &uarr;</a></h2>',
        _overlap_table(result, names),
        _comparisons(result),
        "</section>",
        '<section id="plausibility"><h2>Deformation plausibility and coverage '
        '<a class="top" href="#contents">contents &uarr;</a></h2>',
        _plausibility_table(result, names),
        "</section>",
        '<section id="frames"><h2>Frame-estimate spread <a class="top" href="#contents">'
        "contents &uarr;</a></h2>",
        _frames_table(result, names),
        "</section>",
        *[_registration_section(result, n, slugs[n]) for n in names],
        '<section id="inputs"><h2>Inputs <a class="top" href="#contents">contents &uarr;</a></h2>',
        _inputs_section(result),
        "</section>",
        '<section id="options"><h2>Options <a class="top" href="#contents">contents &uarr;'
        "</a></h2>",
        _options_section(result),
        "</section>",
        "<footer>Written by itk-nrreval: one self-contained file (figures embedded, no "
        "script, no network). The numbers are those of results.json beside it.</footer>",
        "</main>",
    ]
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>Registration evaluation: {_e(', '.join(names))}</title>"
        f"<style>{_CSS}</style></head><body>\n" + "\n".join(body) + "\n</body></html>\n"
    )
