"""``report.html``: one self-contained page that reads an evaluation, as MRIQC and fMRIPrep
reports are read.

The page opens from disk with no network and no JavaScript: every figure is a PNG embedded as
a ``data:`` URI, the style sheet is inline, and the only links are to the page's own
sections. It gives, in order: the verdict in words, with the subjects left off the common
grid and how many subjects each registration flags; the scores with their legend, units and
intervals; the summary figures (the same PNG bytes as the files beside it, ``subjects.png``
among them: every subject's model-distance z-score); per registration first its flagged
subjects (:mod:`itk_nrreval.subject_qc`: name, diagnosis and flags in words, the subject in
the common frame beside the mean image and a checkerboard of the two), then its mean image,
a checkerboard of two subjects, the label contours of one subject with a colour legend, a
log-Jacobian-determinant map and the histogram of log det J over all subjects; deformation
plausibility and coverage; the frame-estimate spread; the inputs and the options.

It stays light whatever the number of images N: every picture is a middle slice shrunk to at
most 256 pixels a side (:attr:`EvaluationResult.thumbnails
<itk_nrreval.evaluation.EvaluationResult.thumbnails>`, gathered by the pipeline: of subjects
0 and 1, and of the flagged subjects shown, at most
:data:`~itk_nrreval.reports.FLAGGED_SUBJECTS_SHOWN` per registration), and there is a
bounded number of pictures per registration; only the list of input files grows with N.

:meth:`EvaluationResult.write <itk_nrreval.evaluation.EvaluationResult.write>` writes it
through :func:`itk_nrreval.reports.write_reports`; this module takes the result without
importing its class (that import would be a cycle).

``validate`` and ``sweep`` write a page of the same build beside their JSON
(:func:`validation_report_html`, :func:`sweep_report_html`, from
:meth:`ValidationResult.write <itk_nrreval.validation.ValidationResult.write>` and
:func:`itk_nrreval.sweep.sweep`): the same banner, contents, sections, tables, legends and
embedded figures (``_page``, ``_section``, ``_table``, ``_legend_list``, ``_figure``).
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
    FLAGGED_SUBJECTS_SHOWN,
    TIES_WORDS,
    draw_label_contours,
    figure_pngs,
    format_number,
    format_percent,
    format_rank,
    frame_spread_flagged,
    frame_spread_words,
    middle_slice,
    png_bytes,
    specificity_units,
    thumbnail,
)

__all__ = ["report_html", "validation_report_html", "sweep_report_html"]

#: The overlap weightings the tables show (every one further down): each label counts the same.
_TABLE_OVERLAPS = ("overlap.inverse_volume", "overlap.inverse_volume_complexity")
_DPI = 100  # pixels per inch of the per-registration figures
_OUTSIDE = (0.72, 0.83, 1.0)  # pale blue: no value there (outside the field of view)

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

# The tables must fit a 1280 px window (with its scroll bar) in wide fonts such as DejaVu
# Sans, or the Flags column ends up behind a sideways scroll (tests/test_report_browser.py
# measures this in Chromium). Hence: a page 1240 px wide at most, 5 px cell padding, and
# names (a row's first cell) and file paths (code) that break anywhere, since names such as
# "groupwise_bspline_grid8mm" have no space to break at; numbers never break.
_CSS = """
body{font-family:-apple-system,'Segoe UI',Helvetica,Arial,sans-serif;margin:0;color:#222;
background:#fafafa;line-height:1.45;overflow-wrap:break-word}
main{max-width:1240px;margin:0 auto;padding:0 24px 48px}
header{background:#2c3e50;color:#fff;padding:18px 24px}
header h1{margin:0;font-size:1.6em}header p{margin:4px 0 0;color:#d5dde5}
h2{border-bottom:2px solid #2c3e50;padding-bottom:4px;margin-top:36px}
h3{margin-bottom:4px}
nav ol{columns:2;margin:0}a{color:#1f5f99}nav a,a.top{color:#1f5f99;text-decoration:none}
nav a:hover{text-decoration:underline}
a.top{font-size:.85em;float:right;font-weight:normal}
.verdict{background:#eaf4ea;border-left:6px solid #2e7d32;padding:10px 16px;font-size:1.1em}
.verdict.flagged{background:#fdf0e6;border-left-color:#d9822b}
table{border-collapse:collapse;margin:8px 0 12px;font-size:.9em;background:#fff}
th,td{border:1px solid #ccd;padding:3px 5px;text-align:right;vertical-align:top}
th{background:#e8edf2}td:first-child,th:first-child{text-align:left}
td{white-space:nowrap}td.text{text-align:left;max-width:420px;white-space:normal}
td.text:first-child,td.text code{overflow-wrap:anywhere}
tr.flagged td{background:#fff4ec}tr.best td{background:#eaf4ea}
dl.legend{font-size:.88em;background:#fff;border:1px solid #dde;padding:8px 14px;
columns:2;column-gap:28px}
dl.legend dt,dl.legend dd{break-inside:avoid}dl.legend dt{break-after:avoid}
dl.legend dt{font-weight:bold;margin-top:6px}dl.legend dd{margin-left:18px}
figure{margin:12px 12px 12px 0;background:#fff;border:1px solid #dde;padding:8px;
display:inline-table;vertical-align:top}
figure img{max-width:100%;height:auto;display:block}
figure.half img{max-width:560px}
figcaption{font-size:.86em;color:#444;display:table-caption;caption-side:bottom;
background:#fff;border:1px solid #dde;border-top:0;padding:4px 8px 8px}
.flag{color:#b34700;font-weight:bold}a.flag{white-space:nowrap}
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


def _table(
    head: Sequence[str],
    rows: Sequence[Sequence[str]],
    *,
    text: Sequence[int] = (0,),
    classes: Sequence[str] | None = None,
    ids: Sequence[str] | None = None,
    wide: bool = False,
) -> str:
    """An HTML table of cells already in HTML.

    Parameters
    ----------
    head : sequence of str
        Column headings (HTML); empty for a table of rows headed by their first cell.
    rows : sequence of sequence of str
        The cells (HTML), one sequence per row.
    text : sequence of int
        Columns of words, left-aligned and wrapped (negative counts from the end); the
        others are numbers, right-aligned.
    classes, ids : sequence of str, optional
        Per row, a CSS class (e.g. ``"flagged"``) and an id (a link target); "" for none.
    wide : bool
        Scroll sideways rather than overflow the page (many columns).
    """
    out = []
    if head:
        out.append("<thead><tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr></thead>")
    out.append("<tbody>")
    for k, cells in enumerate(rows):
        words = {i % len(cells) for i in text}
        cls = classes[k] if classes else ""
        rid = ids[k] if ids else ""
        attrs = (f' class="{cls}"' if cls else "") + (f' id="{rid}"' if rid else "")
        tds = "".join(
            f'<td class="text">{c}</td>' if i in words else f"<td>{c}</td>"
            for i, c in enumerate(cells)
        )
        out.append(f"<tr{attrs}>{tds}</tr>")
    out.append("</tbody>")
    table = "<table>" + "".join(out) + "</table>"
    return f'<div class="wide">{table}</div>' if wide else table


def _key_value_table(rows: Sequence[tuple[str, str]]) -> str:
    """A two-column table of (name, HTML value), names as row headings."""
    body = "".join(f'<tr><th>{_e(k)}</th><td class="text">{v}</td></tr>' for k, v in rows)
    return f"<table><tbody>{body}</tbody></table>"


def _legend_list(items: Sequence[tuple[str, str]]) -> str:
    """A legend of terms: (term, HTML definition) pairs, in two columns."""
    body = "".join(f"<dt>{_e(k)}</dt><dd>{v}</dd>" for k, v in items)
    return f'<dl class="legend">{body}</dl>'


def _section(sid: str, title: str, *parts: str) -> str:
    """A section the contents link to, headed by `title` and a link back to the contents."""
    return (
        f'<section id="{sid}"><h2>{_e(title)} <a class="top" href="#contents">contents '
        "&uarr;</a></h2>\n" + "\n".join(p for p in parts if p) + "\n</section>"
    )


def _page(
    *,
    title: str,
    heading: str,
    subtitle: str,
    sections: Sequence[tuple[str, str, str]],
    footer: str,
) -> str:
    """The whole page: header, contents, the sections in order, footer.

    Parameters
    ----------
    title : str
        The browser tab's title (plain text).
    heading, subtitle : str
        The banner's title (plain text) and the line under it (HTML).
    sections : sequence of (str, str, str)
        ``(id, heading, body HTML)``; the contents list them in this order.
    footer : str
        HTML.
    """
    nav = "".join(f'<li><a href="#{sid}">{_e(t)}</a></li>' for sid, t, _ in sections)
    body = [
        f"<header><h1>{_e(heading)}</h1><p>{subtitle}</p></header>",
        "<main>",
        f'<nav id="contents"><h2>Contents</h2><ol>{nav}</ol></nav>',
        *[_section(sid, t, html_) for sid, t, html_ in sections],
        f"<footer>{footer}</footer>",
        "</main>",
    ]
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>{_e(title)}</title>"
        f"<style>{_CSS}</style></head><body>\n" + "\n".join(body) + "\n</body></html>\n"
    )


_SELF_CONTAINED = (
    "Written by itk-nrreval: one self-contained file (figures embedded, no script, no network)."
)


def _slugs(names: Sequence[str], prefix: str = "reg-") -> dict[str, str]:
    """An id per name: `prefix` and the name's letters, digits, ``-`` and ``_``."""
    out: dict[str, str] = {}
    used: set[str] = set()
    for name in names:
        base = prefix + (re.sub(r"[^A-Za-z0-9_-]+", "-", name).strip("-") or "x")
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
    rel = result.relative_ranks[measure][name]
    # the rank on a line of its own: "100.0% (1 (tied))" on one line widened the table past
    # the page
    return f"{format_percent(rel)}<br><small>rank {format_rank(result, measure, name)}</small>"


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


def _label_values(result) -> list[int]:
    """Every nonzero label value of subject 0's thumbnails, over all registrations: one
    colour per value in every figure of the report."""
    values: set[int] = set()
    for t in result.thumbnails.values():
        if "labels_0" in t:
            values |= {int(v) for v in np.unique(thumbnail(t["labels_0"], mode="nearest"))}
    values.discard(0)
    return sorted(values)


def _grey_panels(
    panels: Sequence[tuple[str, np.ndarray]], *, aspect: float, legend: bool, inches: float = 2.7
):
    """A row of images on one grey scale, titled, without ticks.

    Parameters
    ----------
    panels : sequence of (str, ndarray)
        Each panel's title and 2D image (intensity units; NaN outside a field of view,
        drawn pale blue).
    aspect : float
        Pixel height over width (:func:`_aspect`).
    legend : bool
        Leave room on the right for a legend.
    inches : float
        Width of a panel (inches; 100 pixels each in the page).

    Returns
    -------
    (matplotlib.figure.Figure, sequence of Axes)
    """
    from matplotlib import colormaps
    from matplotlib.figure import Figure

    fig = Figure(figsize=(inches * len(panels) + (0.9 if legend else 0.0), inches * 3.0 / 2.7))
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    lo, hi = _grey_limits(*[p for _, p in panels])
    # outside an image's field of view (NaN) in a colour no image or contour has
    grey = colormaps["gray"].with_extremes(bad=_OUTSIDE)
    for ax, (title, arr) in zip(axes, panels, strict=True):
        ax.imshow(arr, cmap=grey, vmin=lo, vmax=hi, origin="lower", aspect=aspect)
        ax.set_title(title, fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.subplots_adjust(wspace=0.05)
    return fig, axes


def _images_figure(result, name: str):
    """Mean image, checkerboard of subjects 0 and 1, subject 0 with its label contours.

    Returns
    -------
    matplotlib.figure.Figure
    """
    t = result.thumbnails.get(name, {})
    mean = thumbnail(middle_slice(result.mean_images[name]))
    aspect = _aspect(t.get("common_spacing"))
    panels = [("mean", mean)]
    if "image_0" in t and "image_1" in t:
        panels.append(("checker", _checkerboard(thumbnail(t["image_0"]), thumbnail(t["image_1"]))))
    if "image_0" in t:
        panels.append(("subject", thumbnail(t["image_0"])))
    legend = "labels_0" in t
    titles = {
        "mean": f"mean of the {result.scores[name].specificity.n_images} images",
        "checker": "checkerboard: subjects 0 | 1",
        "subject": "subject 0" + (" and its labels" if legend else ""),
    }
    fig, axes = _grey_panels(
        [(titles[kind], arr) for kind, arr in panels], aspect=aspect, legend=legend
    )
    if legend:
        draw_label_contours(
            axes[-1],
            thumbnail(t["labels_0"], mode="nearest"),
            aspect=aspect,
            values=_label_values(result),
        )
    return fig


def _subject_figure(result, name: str, index: int):
    """A subject in the common frame, the registration's mean image, and a checkerboard of
    the two (the subject on the first tile), on one grey scale.

    Parameters
    ----------
    result : EvaluationResult
    name : str
        The registration.
    index : int
        The subject (manifest index); its slice must be among the thumbnails
        (``image_<index>``: the pipeline keeps those of the flagged subjects the report
        shows).

    Returns
    -------
    matplotlib.figure.Figure
    """
    t = result.thumbnails[name]
    subject = thumbnail(t[f"image_{index}"])
    mean = thumbnail(middle_slice(result.mean_images[name]))
    fig, _ = _grey_panels(
        [
            (f"subject {index}", subject),
            ("mean image", mean),
            ("checkerboard of the two", _checkerboard(subject, mean)),
        ],
        aspect=_aspect(t.get("common_spacing")),
        legend=False,
        inches=1.9,  # two subjects side by side in the page
    )
    return fig


def _jacobian_figure(result, name: str):
    """log det J of subject 0 (map, colour bar, folded voxels) and the histogram of all.

    Returns
    -------
    matplotlib.figure.Figure or None
        None without a Jacobian summary (no thumbnails).
    """
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
    return fig


# ----------------------------------------------------------------------------- sections


def _value_ci(value: float, iv) -> str:
    """A score over its subject-level 95% interval (small, below)."""
    return f'{format_number(value)}<br><span class="ci">{_ci(iv)}</span>'


def _scores_table(result, names: Sequence[str], slugs: Mapping[str, str]) -> str:
    overlaps = [m for m in _TABLE_OVERLAPS if m in result.ranks]
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
    classes = ["flagged" if result.scores[n].flags else "" for n, _ in rows]
    return _table(head, [c for _, c in rows], text=(0, -1), classes=classes, wide=True)


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
            "it is <b>not a rank</b>. The rank (1 = best) is below it. " + _e(TIES_WORDS),
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
            "registration keeps its scores; a flag is a warning, not a decision (only severe "
            "folding decides against it: see the verdict).",
        ),
    ]
    return _legend_list(items)


def _overlap_table(result, names: Sequence[str]) -> str:
    ws = [m.split(".", 1)[1] for m in result.measures if m.startswith("overlap.")]
    if not ws:
        return ""
    head = ["Registration"]
    for w in ws:
        head += [f"{_e(w.replace('_', ' '))}<br>[95% CI]", "Rel. (rank)"]
    rows = []
    for n in names:
        s = result.scores[n]
        row = [_e(n)]
        for w in ws:
            row += [
                _value_ci(s.overlap[w], s.intervals.get(f"overlap.{w}")),
                _rel(result, f"overlap.{w}", n),
            ]
        rows.append(row)
    words = "".join(
        f"<li><b>{_e(w.replace('_', ' '))}</b>: {_e(_WEIGHTING_WORDS.get(w, w))}</li>" for w in ws
    )
    return (
        "<h3>Overlap by label weighting</h3>" + _table(head, rows, wide=True) + f"<ul>{words}</ul>"
    )


def _comparisons(result) -> str:
    comps = list(result.comparisons)
    if not comps:
        return "<p>No pairwise differences: confidence was not computed.</p>"
    rows = [
        [
            _e(c.measure),
            f"{_e(c.a)} &minus; {_e(c.b)}",
            format_number(c.difference),
            f"[{format_number(c.ci95[0])}, {format_number(c.ci95[1])}]",
            "yes" if c.separable else "no",
        ]
        for c in comps
    ]
    head = ["Measure", "a &minus; b", "Difference", "95% CI", "Separable (CI excludes 0)"]
    return (
        "<details><summary>Pairwise differences with their subject-level 95% intervals "
        f"({len(comps)})</summary>" + _table(head, rows, text=(0, 1)) + "</details>"
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
        rows.append([_e(n), *cells, flags])
    th = result.options.get("thresholds", {})
    head = ["Registration", "Folded voxels (mean)", "Folded (worst image)", "SDlogJ"]
    head += ["det J min", "det J max", "Inverse consistency (mm)", "Coverage, all images"]
    head += ["Coverage, least image", "In words"]
    classes = ["flagged" if result.scores[n].flags else "" for n in names]
    return (
        _table(head, rows, text=(0, -1), classes=classes, wide=True) + '<dl class="legend">'
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
            [
                _e(n),
                _e(_FRAME_WORDS.get(f.method, f.method)),
                format_number(f.spread_mean_mm, 3),
                "flagged" if frame_spread_flagged(result, n) else "no",
                format_number(f.spread_max_mm, 3),
            ]
        )
    head = ["Registration", "Brought into the common frame by"]
    head += ["Spread, mean (mm)", "Mean above the flag threshold", "Spread, max (mm)"]
    return (
        _table(head, rows, text=(0, 1))
        + "<p>Each registration has its own reference frame and is brought "
        f"into the common frame (<b>{_e(result.common_frame)}</b>'s) by a transform F. Each "
        "image gives its own estimate F<sub>i</sub> of it; the spread is how far those "
        "estimates lie from F (|F<sub>i</sub>(p) &minus; F(p)| over the images and the "
        f"voxels of the common grid, inside the mask). {_e(frame_spread_words(result)[1])}</p>"
    )


def _flagged_subjects(result, name: str) -> str:
    """The flagged subjects of a registration: how many, then for each of the first
    :data:`~itk_nrreval.reports.FLAGGED_SUBJECTS_SHOWN` (manifest order) its name, diagnosis
    and flags in words and its picture beside the mean image; a line for the rest."""
    s = result.scores[name]
    if not s.subjects:
        return ""  # not assessed (a result of an earlier version)
    flagged = s.flagged_subjects
    n = len(s.subjects)
    if not flagged:
        return f"<h3>Flagged subjects</h3><p>None of the {n} subjects is flagged.</p>"
    where = "the middle slice of " if result.mean_images[name].ndim == 3 else ""
    parts = [
        f"<h3>Flagged subjects: {len(flagged)} of the {n} subjects flagged</h3>"
        "<p>Each subject compared with the rest of the cohort under this registration "
        "(robust z-scores, z = (x &minus; median) / (1.4826 MAD)): its distance to the "
        "texture model of the others, its deformation, its label overlap with the others, "
        "its coverage of the common grid. Every subject's values are in "
        "<code>subjects.csv</code>; every z-score in "
        f'<a href="#figures">subjects.png</a>. The pictures: {where}the subject resampled '
        "into the common frame, the mean of the N images, and a checkerboard of the two "
        "(the subject on the first tile): where the subject is aligned, edges run on across "
        "the tile borders. One grey scale per picture; pale blue: outside the subject's "
        "field of view.</p>"
    ]
    t = result.thumbnails.get(name, {})
    for q in flagged[:FLAGGED_SUBJECTS_SHOWN]:
        cause = q.diagnosis if q.diagnosis is not None else "no common cause recognised"
        words = (
            f"<b>{_e(_subject(result, q.index))}</b><br><b>Diagnosis:</b> {_e(cause)}.<br>"
            "<b>Flags:</b> " + "; ".join(_e(f) for f in q.flags) + "."
        )
        if f"image_{q.index}" in t:
            png = png_bytes(_subject_figure(result, name, q.index), dpi=_DPI)
            parts.append(_figure(png, f"{name}: subject {q.index}", words))
        else:  # thumbnails of an earlier version, or a result put together in memory
            parts.append(f"<p>{words}<br>(No picture: its resampled slice was not kept.)</p>")
    rest = len(flagged) - FLAGGED_SUBJECTS_SHOWN
    if rest > 0:
        parts.append(
            f"<p>{rest} more flagged subject{'s' if rest > 1 else ''}, not shown: "
            "<code>subjects.csv</code> and <code>summary.md</code> list every one.</p>"
        )
    return "\n".join(parts)


def _registration_section(result, name: str) -> str:
    """The body of a registration's section: its flagged subjects, its scores in a line,
    its two figures."""
    s = result.scores[name]
    t = result.thumbnails.get(name, {})
    parts = [_flagged_subjects(result, name), "<h3>Scores, images and deformation</h3>"]
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
            "(colour legend: label values). Common grey scale in the images' intensity units; "
            "pale blue: outside that image's field of view."
        )
        if "image_1" not in t:
            cap = f"Left: {where}the mean image. Right: {_e(s0)}."
    else:
        cap = f"{where.capitalize()}the mean of the N resampled images in the common frame."
    images = png_bytes(_images_figure(result, name), dpi=_DPI)
    parts.append(_figure(images, f"{name}: images", cap))
    jac = _jacobian_figure(result, name)
    if jac is not None:
        parts.append(
            _figure(
                png_bytes(jac, dpi=_DPI),
                f"{name}: Jacobian determinant",
                f"Left: log of the Jacobian determinant of {_e(_subject(result, 0))}'s "
                f"transform on {where}the registration's own reference grid (blue: local "
                "shrinking, red: growth, black: folding, grey: outside the mask). Right: "
                "histogram of log det J over every voxel of every subject (inside the mask), "
                "64 bins over [-2, 2]; the share beyond the bins and folded is printed.",
            )
        )
    return "\n".join(parts)


def _subjects_in_verdict(result, names: Sequence[str], slugs: Mapping[str, str]) -> str:
    """The verdict area's lines on the subjects: those left off the common grid (in no
    registration's scores), and how many each registration flags, linked to its section."""
    out = []
    left_out = result.options.get("left_out_of_scores") or []
    if left_out:
        who = ", ".join(_e(_subject(result, i)) for i in left_out)
        out.append(
            f"<p><b>Left out of every registration's scores</b> (off the common grid: its "
            f"transform maps the image (almost) outside it): {who}.</p>"
        )
    counts = []
    for n in names:
        subjects = result.scores[n].subjects
        if subjects:
            k = len(result.scores[n].flagged_subjects)
            what = f"{k} of {len(subjects)} subjects flagged" if k else "no subject flagged"
            counts.append(f'<a href="#{slugs[n]}">{_e(n)}</a>: {what}')
    if counts:
        out.append(
            "<p>Flagged subjects (each registration's section names them): "
            + "; ".join(counts)
            + ".</p>"
        )
    return "".join(out)


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
    out = [_key_value_table(rows)]
    regs = inp.get("registrations") or {}
    if regs:
        head = ["Registration", "Reference", "Reference index", "Frame transform"]
        head.append("Transforms (first image)")
        cells = []
        for name, r in regs.items():
            first = (r.get("transforms") or [[]])[0]
            cells.append(
                [
                    _e(name),
                    item(r.get("reference")),
                    _item_text(r.get("reference_index")),
                    item(r.get("frame_transform")),
                    ", ".join(item(x) for x in first),
                ]
            )
        out.append(_table(head, cells, text=(0, 1, 3, 4), wide=True))
    listing = "".join(
        f"<li>{item(p)}" + (f" &mdash; labels {item(labels[i])}" if labels else "") + "</li>"
        for i, p in enumerate(images)
    )
    out.append(
        f"<details><summary>The {len(images)} images (subject i is the i-th)</summary>"
        f"<ol start='0'>{listing}</ol></details>"
    )
    return "\n".join(out)


def _flat(d: Mapping, prefix: str = "") -> list[tuple[str, object]]:
    """Nested mappings as ``(dotted.name, value)`` pairs."""
    out = []
    for k, v in d.items():
        if isinstance(v, Mapping):
            out += _flat(v, f"{prefix}{k}.")
        else:
            out.append((f"{prefix}{k}", v))
    return out


def _item_text(value) -> str:
    """A value of the inputs or options for a reader: a dash when not set (None)."""
    return "–" if value is None else _e(value)


def _options_table(options: Mapping) -> str:
    """Every option, nested ones dotted, values as code (a dash when not set)."""
    return _key_value_table(
        [(k, "–" if v is None else f"<code>{_e(v)}</code>") for k, v in _flat(options)]
    )


def _options_section(result) -> str:
    run = {f"run.{k}": v for k, v in dict(result.run).items()}
    return _options_table({**dict(result.options), **run, "version": result.version})


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

    flagged = any(result.scores[n].flags for n in names)
    verdict = (
        "".join(f"<p>{_e(line)}</p>" for line in result.verdict.text)
        if result.verdict is not None
        else "<p>No verdict was computed.</p>"
    )
    ranking = " &rarr; ".join(f'<a href="#{slugs[n]}">{_e(n)}</a>' for n in names)
    subjects = _subjects_in_verdict(result, names, slugs)

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
        "subjects.png": (
            "Every subject in the scores, per registration: the robust z-score of its log "
            "distance to the texture model of the other subjects (0: a typical subject; "
            "above the dashed line the distance alone flags it). Red: flagged for any reason "
            "(a duplicated image lies far below: too close to another), numbered by subject "
            "for those each registration's section shows. Subjects left off the common grid "
            "have no score and are not drawn."
        ),
    }
    for fname, png in figures.items():
        css = "" if fname == "mean_images.png" else "half"
        fig_parts.append(_figure(png, fname, captions.get(fname, _e(fname)), css=css))

    subtitle = (
        f"{len(names)} registrations of N = {n_images} images, compared in the frame of "
        f"<b>{_e(result.common_frame)}</b>; itk-nrreval {_e(result.version)}"
    )
    sections = [
        (
            "verdict",
            "Verdict",
            f'<div class="verdict{" flagged" if flagged else ""}">{verdict}</div>'
            f"<p>Ranking (by level of the decisions: first the registrations no other is "
            f"decided better than; by specificity within a level): {ranking}</p>" + subjects,
        ),
        (
            "scores",
            "Scores, with their legend",
            "<p>Rows in the verdict's order. Each registration's name links to its section."
            "</p>" + _scores_table(result, names, slugs) + _legend(result),
        ),
        ("figures", "Summary figures", "".join(fig_parts)),
        *[(slugs[n], f"Registration: {n}", _registration_section(result, n)) for n in names],
        (
            "details",
            "Every overlap weighting and pairwise difference",
            _overlap_table(result, names) + _comparisons(result),
        ),
        (
            "plausibility",
            "Deformation plausibility and coverage",
            _plausibility_table(result, names),
        ),
        ("frames", "Frame-estimate spread", _frames_table(result, names)),
        ("inputs", "Inputs", _inputs_section(result)),
        ("options", "Options", _options_section(result)),
    ]
    return _page(
        title=f"Registration evaluation: {', '.join(names)}",
        heading="Registration evaluation",
        subtitle=subtitle,
        sections=sections,
        footer=f"{_SELF_CONTAINED} The numbers are those of results.json beside it.",
    )


# ----------------------------------------------------------------------------- validate


def _r_words(r: float, ci: tuple[float, float]) -> str:
    """Whether specificity rises as overlap falls, from Pearson r and its 95% interval."""
    lo, hi = ci
    if not math.isfinite(r):
        return "undefined (fewer than two values of d in the fit, or no spread)"
    if math.isfinite(hi) and hi < 0:
        return "yes: specificity rises as overlap falls"
    if r < 0:
        return "only weakly: r is negative but its 95% interval reaches 0"
    return "no: specificity does not rise as overlap falls"


def _fmt_ci(ci: tuple[float, float]) -> str:
    lo, hi = ci
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return "–"
    return f"[{lo:.3f}, {hi:.3f}]"


def _d_id(d: float) -> str:
    return "d-" + f"{d:g}".replace(".", "_")


def validation_report_html(
    result, *, figures: Mapping[str, bytes], units: str, version: str | None = None
) -> str:
    """The text of ``report.html`` for a :class:`~itk_nrreval.validation.ValidationResult`.

    The verdict in words first (does specificity rise as overlap falls: Pearson r with its
    95% interval per label weighting, the Spearman correlation of the mean specificity with
    the displacement d, the sensitivity), then the table by d (mean and SD over the
    repeats), the figures, every perturbed set, and the parameters.

    Parameters
    ----------
    result : ValidationResult
    figures : mapping of str to bytes
        PNG bytes: ``"fig2_<weighting>"`` (:func:`~itk_nrreval.validation.fig2_figure`) per
        weighting and ``"vs_d"`` (:func:`~itk_nrreval.validation.vs_d_figure`), the same
        bytes as the files written beside the page.
    units : str
        What specificity is measured in, e.g. ``"L1 distance, intensity units"``.
    version : str, optional
        The package version, printed in the header.

    Returns
    -------
    str
        One self-contained HTML5 page, as :func:`report_html`'s.
    """
    s = result.summary
    m = result.means()
    w0 = result.weightings[0]
    fit_from = result.parameters["fit_from"]
    sec = result.parameters.get("section")
    where = f", slice {sec['axis']}:{sec['index']}" if sec else ""
    grid = " × ".join(map(str, result.shape[::-1]))
    r0 = s.pearson_r.get(w0, math.nan)
    ci0 = s.pearson_ci.get(w0, (math.nan, math.nan))
    answer = _r_words(r0, ci0)
    good = math.isfinite(ci0[1]) and ci0[1] < 0
    verdict = [
        f"<p><b>Does specificity rise as the registration is made worse? {_e(answer[0].upper())}"
        f"{_e(answer[1:])}.</b></p>",
        f"<p>Pearson r between specificity and the {_e(w0.replace('_', ' '))} overlap: "
        f"<b>{format_number(r0, 3)}</b>, 95% interval {_fmt_ci(ci0)} (Fisher's z), over the "
        f"{s.n_fit} perturbed sets with d &ge; {fit_from:g} px (strongly negative is good: "
        "the paper's Fig. 2 line).</p>",
        f"<p>Spearman correlation of the mean specificity with d (d &ge; {fit_from:g} px): "
        f"<b>{format_number(s.spearman, 3)}</b>; the mean rises strictly with d: "
        f"<b>{'yes' if s.monotonic else 'no'}</b>. Sensitivity: "
        f"{format_number(s.sensitivity, 3)} Monte-Carlo standard errors per pixel of d"
        + (
            f" ({format_number(s.sensitivity_mm, 3)} per mm)"
            if math.isfinite(s.sensitivity_mm)
            else ""
        )
        + ".</p>",
    ]
    if s.unperturbed is not None:
        verdict.append(
            f"<p>Unperturbed specificity (d = 0): {format_number(s.unperturbed)}. Below "
            f"d = {fit_from:g} px the paper finds a dip under it (interpolation smooths the "
            "images), which is why the fit starts there.</p>"
        )

    levels = m["displacement"]
    head = ["d (px)", "d (mm)", "Specificity<br>mean &plusmn; SD", "MC s.e.<br>(mean)"]
    head += [f"Overlap, {_e(w.replace('_', ' '))}<br>mean &plusmn; SD" for w in result.weightings]
    head += ["In the fit"]
    rows = []
    for k, d in enumerate(levels):
        row = [
            f"{d:g}",
            format_number(m["displacement_mm"][k], 3),
            f"{format_number(m['specificity'][k])} &plusmn; "
            f"{format_number(m['specificity_sd'][k], 2)}",
            format_number(m["specificity_stderr"][k], 2),
        ]
        row += [
            f"{format_number(m[f'overlap_{w}'][k])} &plusmn; "
            f"{format_number(m[f'overlap_{w}_sd'][k], 2)}"
            for w in result.weightings
        ]
        row.append("yes" if d >= fit_from else "no")
        rows.append(row)
    table = _table(head, rows, text=(), ids=[_d_id(d) for d in levels], wide=True)
    legend = _legend_list(
        [
            (
                "d",
                "the mean displacement of every image's random clamped-plate-spline warp, in "
                "pixels of the grid (and in mm, the mean over the warps); d = 0 is the "
                "registered set itself.",
            ),
            (
                "Specificity",
                f"of the perturbed set's texture model ({_e(units)}; M = "
                f"{result.n_samples:,} samples, seed {result.seed}); <b>lower is better</b>. "
                f"Mean and standard deviation over the {result.parameters.get('repeats', '')} "
                "repeats at each d.",
            ),
            (
                "MC s.e.",
                "Monte-Carlo standard error of one specificity estimate (finite M only), "
                "mean over the repeats.",
            ),
            (
                "Overlap",
                "generalized Tanimoto overlap of the perturbed label memberships, 0 to 1, "
                "<b>higher is better</b>, per label weighting.",
            ),
            ("In the fit", f"whether d &ge; {fit_from:g} px: the rows the line and r use."),
        ]
    )
    stats_head = ["Label weighting", "Pearson r", "95% CI", "Fit: slope a", "Fit: intercept b"]
    stats_rows = [
        [
            _e(w.replace("_", " ")),
            format_number(s.pearson_r.get(w, math.nan), 3),
            _fmt_ci(s.pearson_ci.get(w, (math.nan, math.nan))),
            format_number(s.fit.get(w, (math.nan, math.nan))[0]),
            format_number(s.fit.get(w, (math.nan, math.nan))[1]),
        ]
        for w in result.weightings
    ]
    correlations = (
        _table(stats_head, stats_rows)
        + "<p>The line is specificity = a &times; overlap + b, least squares over the sets "
        f"with d &ge; {fit_from:g} px.</p>"
    )
    figs = []
    for w in result.weightings:
        key = f"fig2_{w}"
        if key in figures:
            figs.append(
                _figure(
                    figures[key],
                    f"Fig. 2, {w}",
                    f"The paper's Fig. 2, {_e(w.replace('_', ' '))} weighting: each point one "
                    "perturbed set, coloured by d (legend, in pixels); error bars &plusmn;1 "
                    "Monte-Carlo s.e. of its specificity (the title says when they are "
                    f"smaller than the markers); grey: the line fitted over d &ge; {fit_from:g}"
                    " px; dashed: the unperturbed specificity.",
                    css="half",
                )
            )
    if "vs_d" in figures:
        figs.append(
            _figure(
                figures["vs_d"],
                "specificity and overlap against d",
                "Mean specificity (left) and overlap (right) against d; error bars &plusmn;1 "
                "standard deviation over the repeats (the titles say when they hide behind "
                "the markers).",
            )
        )
    every = _table(
        ["d (px)", "Repeat", "Specificity", "MC s.e."]
        + [f"Overlap, {_e(w.replace('_', ' '))}" for w in result.weightings]
        + ["min det J", "d (mm)"],
        [
            [
                f"{r.displacement:g}",
                str(r.repeat),
                format_number(r.specificity),
                format_number(r.specificity_stderr, 2),
                *[format_number(r.overlap.get(w, math.nan)) for w in result.weightings],
                format_number(r.min_jacobian, 3),
                format_number(r.displacement_mm, 3),
            ]
            for r in result.rows
        ],
        text=(),
    )
    params = {
        "source": result.source,
        "n_images": result.n_images,
        "shape (x, y[, z])": " × ".join(map(str, result.shape[::-1])),
        "spacing (mm)": result.spacing,
        "n_samples (M)": result.n_samples,
        "specificity in": units,
        "n_knots": result.n_knots,
        "seed": result.seed,
        "weightings": ", ".join(result.weightings),
        **{f"parameters.{k}": v for k, v in _flat(dict(result.parameters))},
    }
    if version is not None:
        params["version"] = version
    sections = [
        ("verdict", "Verdict", f'<div class="verdict{"" if good else " flagged"}">'
         + "".join(verdict) + "</div>"),
        ("table", "Specificity and overlap by displacement", table + legend + correlations),
        ("figures", "Figures", "".join(figs)),
        (
            "rows",
            "Every perturbed set",
            f"<details><summary>The {len(result.rows)} perturbed sets</summary>{every}"
            "</details>",
        ),
        ("parameters", "Inputs and parameters", _options_table(params)),
    ]  # fmt: skip
    return _page(
        title=f"Validation: {result.source}",
        heading="Validation: specificity under known misregistration",
        subtitle=(
            f"{len(result.rows)} perturbed sets of N = {result.n_images} images of {grid} "
            f"({_e(result.source)}{_e(where)}); specificity: {_e(units)}, M = {result.n_samples:,}"
            + (f"; itk-nrreval {_e(version)}" if version else "")
        ),
        sections=sections,
        footer=f"{_SELF_CONTAINED} The numbers are those of validation.json beside it.",
    )


# ----------------------------------------------------------------------------- sweep


def sweep_report_html(
    result,
    *,
    figures: Mapping[str, bytes],
    truth_measure: str,
    specificity_figure: str = "sweep.png",
) -> str:
    """The text of ``report.html`` for a :class:`~itk_nrreval.sweep.SweepResult`.

    The verdict in words first (the setting specificity recommends, the settings it cannot
    separate from it, the best by overlap and, when the true transforms were known, by the
    true correspondence error), then the table of every setting, the figures, the
    agreement between measures and the options. The evaluation's own ``report.html``
    (per-setting images and Jacobians) is in ``evaluation/`` beside it.

    Parameters
    ----------
    result : SweepResult
    figures : mapping of str to bytes
        PNG bytes by file name: `specificity_figure` (the sweep's figure) and any of the
        evaluation's summary figures (:func:`itk_nrreval.reports.figure_pngs`).
    truth_measure : str
        The key of the true correspondence error in ``result.best_by`` and
        ``result.spearman``.
    specificity_figure : str
        Which of `figures` is the sweep's own.

    Returns
    -------
    str
        One self-contained HTML5 page, as :func:`report_html`'s.
    """
    ev = result.evaluation
    names = [st.name for st in result.settings]
    slugs = _slugs(names, prefix="setting-")
    params = list(result.parameters)
    first = ev.scores[names[0]]
    overlaps = [m for m in first.measures() if m.startswith("overlap.")]
    # the table keeps the evaluation table's two weightings; every one is in the verdict
    shown = [m for m in overlaps if m in _TABLE_OVERLAPS] or overlaps
    units = specificity_units(ev)

    def link(name: str) -> str:
        return f'<a href="#{slugs[name]}">{_e(name)}</a>'

    def values(name: str) -> str:
        st = next(x for x in result.settings if x.name == name)
        return ", ".join(f"{_e(k)} = {_e(v)}" for k, v in st.values.items())

    rec = result.recommended
    others = [n for n in result.not_separable if n != rec]
    if result.decided:
        verdict = [
            f"<p><b>The verdict recommends {link(rec)}</b> ({values(rec)}): decided better "
            "than every other setting.</p>"
        ]
    else:
        verdict = [
            "<p><b>The verdict leaves open</b> "
            + ", ".join(link(n) for n in [rec, *others])
            + f": no setting is decided better than these, and the evidence does not order "
            f"them. {link(rec)} ({values(rec)}) has the lowest specificity among them.</p>"
        ]
    candidates = set(result.not_separable)
    open_pairs = result.evaluation.verdict.open_pairs
    among = [p for p in open_pairs if {p.a, p.b} <= candidates]
    verdict += [
        f"<p>{link(p.a)} and {link(p.b)}: not decided: {_e(p.reason)}.</p>" for p in among[:4]
    ]
    by_best: dict[str, list[str]] = {}  # one line per setting overlap prefers
    for m in overlaps:
        if m in result.best_by:
            by_best.setdefault(result.best_by[m], []).append(m.split(".", 1)[1].replace("_", " "))
    for best, weightings in by_best.items():
        verdict.append(
            f"<p>Best by overlap: {link(best)} ({_e(', '.join(weightings))} weighting"
            f"{'s' if len(weightings) > 1 else ''}).</p>"
        )
    truth = result.truth_error_mm
    if truth is not None:
        best = result.best_by[truth_measure]
        where = (
            "the same setting"
            if best == rec
            else "in the open set"
            if best in result.not_separable
            else "a different setting"
        )
        verdict.append(
            f"<p><b>The truth's choice</b> (lowest true correspondence error): {link(best)}, "
            f"{format_number(truth[best], 3)} mm, {where}; the verdict's choice has "
            f"{format_number(truth[rec], 3)} mm. Spearman correlation over the settings "
            "between specificity and the true error: "
            f"{format_number(result.spearman.get(truth_measure, math.nan), 3)} (1: the same "
            "order).</p>"
        )
    else:
        verdict.append("<p>No true transforms were given: the truth's choice is unknown.</p>")

    head = ["Setting", *[_e(p) for p in params], "Specificity<br>[95% CI]", "MC s.e."]
    head += [f"Overlap, {_e(m.split('.', 1)[1].replace('_', ' '))}<br>[95% CI]" for m in shown]
    if truth is not None:
        head.append("True error (mm)")
    head += ["Verdict says", "Flags"]
    rows, classes = [], []
    for st in result.settings:
        sc = ev.scores[st.name]
        row = [_e(st.name), *[_e(st.values[p]) for p in params]]
        row += [
            _value_ci(sc.specificity.value, sc.intervals.get("specificity")),
            format_number(sc.specificity.stderr, 2),
        ]
        row += [_value_ci(sc.measures()[m], sc.intervals.get(m)) for m in shown]
        if truth is not None:
            row.append(format_number(truth[st.name], 3))
        row.append(
            "&#9733; recommended"
            if st.name == rec
            else "not separable"
            if st.name in result.not_separable
            else "separably worse"
        )
        row.append("; ".join(_e(f) for f in sc.flags) if sc.flags else "none")
        rows.append(row)
        classes.append("flagged" if sc.flags else "best" if st.name == rec else "")
    table = _table(
        head,
        rows,
        text=(0, -2, -1),
        classes=classes,
        ids=[slugs[n] for n in names],
        wide=True,
    )
    legend = _legend_list(
        [
            (
                "Specificity",
                f"of each setting's texture model ({_e(units)}; M = {ev.options['n_samples']:,}"
                f" samples, seed {ev.options['seed']}, the same samples for every setting); "
                "<b>lower is better</b>. 95% CI: subject-level (jackknife over the subjects); "
                "MC s.e.: Monte-Carlo error only.",
            ),
            (
                "Overlap",
                "generalized Tanimoto overlap of the labels in the common frame, 0 to 1, "
                "<b>higher is better</b>; every weighting is in results.json and in "
                "<code>evaluation/report.html</code>.",
            ),
            (
                "True error",
                "mean distance in mm between where the registration and the true transforms "
                "put each point (known for generated data only); lower is better.",
            ),
            (
                "Verdict says",
                "the recommended setting (&#9733;), the open set the verdict cannot order "
                "(none decided better than them), and the rest.",
            ),
            ("Flags", "physically implausible deformations: a warning, not a decision."),
        ]
    )
    captions = {
        specificity_figure: (
            "Each measure against the first swept option (other options as lines); error "
            "bars: subject-level 95% intervals where computed (the titles say when they are "
            "smaller than the markers); ringed: the best by each measure; star: "
            "specificity's choice; red cross: flagged implausible."
        ),
        "mean_images.png": (
            "The mean image of every setting in the common frame, one grey scale, with the "
            "label boundaries of subject 0 (colour legend: label values). Sharper is better "
            "aligned."
        ),
        "specificity.png": "Specificity of every setting, as in the evaluation's report.",
    }
    figs = "".join(
        _figure(png, fname, captions.get(fname, _e(fname))) for fname, png in figures.items()
    )
    agree = _table(
        ["Measure", "Best setting", "Spearman with specificity"],
        [
            [
                _e(m),
                link(best),
                "–" if m == "specificity" else format_number(result.spearman.get(m), 3),
            ]
            for m, best in result.best_by.items()
        ],
        text=(0, 1),
    ) + (
        "<p>Spearman rank correlation over the settings between specificity and each other "
        "measure, counted so that 1 means agreement (lower specificity with higher overlap, "
        "or with lower true error).</p>"
    )
    options = {
        "method": result.method,
        **{f"parameters.{k}": ", ".join(map(str, v)) for k, v in result.parameters.items()},
        "manifest": result.manifest,
        "reused settings": ", ".join(st.name for st in result.settings if st.reused) or "none",
        **{f"evaluation.{k}": v for k, v in _flat(dict(ev.options))},
        "version": ev.version,
    }
    sections = [
        ("verdict", "Verdict", '<div class="verdict">' + "".join(verdict) + "</div>"),
        (
            "settings",
            "Every setting",
            "<p>In grid order (the last option varies fastest).</p>" + table + legend,
        ),
        ("figures", "Figures", figs),
        ("agreement", "Agreement between measures", agree),
        (
            "options",
            "Inputs and options",
            _options_table(options)
            + "<p>The evaluation's own report (each setting's images, Jacobian maps and "
            "frame) is <code>evaluation/report.html</code> beside this file.</p>",
        ),
    ]
    n_images = first.specificity.n_images
    return _page(
        title=f"Sweep: {result.method} {', '.join(params)}",
        heading=f"Parameter sweep: {result.method}",
        subtitle=(
            f"{len(names)} settings of {_e(', '.join(params))} on N = {n_images} images; "
            f"specificity: {_e(units)}, M = {ev.options['n_samples']:,}; itk-nrreval "
            f"{_e(ev.version)}"
        ),
        sections=sections,
        footer=f"{_SELF_CONTAINED} The numbers are those of sweep.json beside it.",
    )
