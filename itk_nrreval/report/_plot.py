"""Plot helpers every report shares: PNG bytes, slices and thumbnails, label contours, error
bars that hide behind their markers, long names wrapped.

matplotlib is imported inside the functions (and only in :mod:`itk_nrreval.report`): no
pyplot, so the process's backend is left alone, and importing the package stays light.
"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping, Sequence

import numpy as np

from ..io.label_names import label_text

__all__ = [
    "png_bytes",
    "middle_slice",
    "thumbnail",
    "LEGEND_LABELS",
    "draw_label_contours",
    "bars_hidden",
    "HIDDEN_BARS",
    "wrap_name",
]


def png_bytes(fig, *, dpi: int = 120) -> bytes:
    """Render a ``matplotlib.figure.Figure`` to compact PNG bytes (tight bounding box).

    Every figure is rendered once: the bytes are written to a file and embedded in the HTML
    report alike. The PNG is stored with a palette when that loses nothing visible: exactly
    when the picture has at most 256 colours, else with an adaptive palette of 256 colours
    only if no channel of any pixel moves by more than 2 of 255 (grey images over a few
    coloured contours); otherwise as true colour. About 3-5 times smaller than matplotlib's
    RGBA output for the report's figures.
    """
    from PIL import Image

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    buf.seek(0)
    with Image.open(buf) as im:
        rgb = im.convert("RGB")
    arr = np.asarray(rgb)
    packed = (arr[..., 0].astype(np.uint32) << 16) | (arr[..., 1].astype(np.uint32) << 8)
    packed |= arr[..., 2]
    colours, index = np.unique(packed, return_inverse=True)
    if colours.size <= 256:
        out = Image.fromarray(index.reshape(packed.shape).astype(np.uint8))
        palette = np.stack([colours >> 16, (colours >> 8) & 255, colours & 255], axis=1)
        out.putpalette(palette.astype(np.uint8).ravel().tolist())
    else:
        out = rgb.quantize(256, method=Image.Quantize.MAXCOVERAGE, dither=Image.Dither.NONE)
        error = np.abs(np.asarray(out.convert("RGB"), np.int16) - arr).max()
        if error > 2:
            out = rgb
    res = io.BytesIO()
    out.save(res, format="PNG", optimize=True)
    return res.getvalue()


def middle_slice(img: np.ndarray) -> np.ndarray:
    """The middle slice (numpy index ``shape[0] // 2``) of a 3D array; a 2D array as is."""
    return img if img.ndim == 2 else img[img.shape[0] // 2]


def thumbnail(a: np.ndarray, *, max_size: int = 256, mode: str = "mean") -> np.ndarray:
    """A 2D array shrunk by a whole factor until no side exceeds `max_size` pixels.

    Parameters
    ----------
    a : ndarray, 2D
    max_size : int
    mode : {"mean", "nearest", "any"}
        ``"mean"``: the mean of each block of pixels, NaN ignored (NaN where a block is all
        NaN); ``"nearest"``: the centre pixel of each block (for label maps); ``"any"``:
        whether any pixel of the block is true (for masks: a folded voxel stays visible).

    Returns
    -------
    ndarray
        `a` itself when it already fits; else of shape ``(rows // f, columns // f)`` in
        every mode (the last rows and columns short of a whole block are dropped), so that
        thumbnails of the same slice overlay pixel for pixel.
    """
    a = np.asarray(a)
    f = math.ceil(max(a.shape) / max_size)
    if f <= 1:
        return a
    h, w = a.shape[0] // f * f, a.shape[1] // f * f  # every mode drops the same remainder
    if mode == "nearest":
        return a[f // 2 : h : f, f // 2 : w : f]
    blocks = a[:h, :w].reshape(h // f, f, w // f, f)
    if mode == "any":
        return blocks.any(axis=(1, 3))
    if mode != "mean":
        raise ValueError(f"mode: {mode!r} is not one of ('mean', 'nearest', 'any')")
    valid = ~np.isnan(blocks)
    count = valid.sum(axis=(1, 3))
    total = np.where(valid, blocks, 0.0).sum(axis=(1, 3))
    return np.divide(total, count, out=np.full(count.shape, np.nan), where=count > 0)


#: Label maps with at most this many label values get one colour and a legend entry each
#: (tab20's colours without its two greys, which would vanish on a grey image).
LEGEND_LABELS = 18


def draw_label_contours(
    ax,
    labels: np.ndarray,
    *,
    aspect: float = 1.0,
    fontsize: int = 6,
    legend: bool = True,
    values: Sequence[int] | None = None,
    names: Mapping[int, str] | None = None,
) -> tuple[list, str]:
    """Draw the boundaries of every nonzero label of `labels` over an image in `ax`.

    Boundary pixels (a nonzero label with a 4-neighbour of another value) are drawn in the
    label's colour, with a legend naming every label value present in `labels`; with more
    than :data:`LEGEND_LABELS` values, all in one colour and one legend entry that says so.

    Parameters
    ----------
    ax : matplotlib Axes
        Already showing the image (``origin="lower"``), on the same pixel grid.
    labels : ndarray of int, 2D
    aspect : float
        Pixel aspect (row spacing / column spacing), as the image's.
    fontsize : int
        Legend font size.
    legend : bool
        Draw the legend beside `ax`; False leaves it to the caller (e.g. one legend for a
        row of panels).
    values : sequence of int, optional
        Every label value of the figure (or the report), present here or not: a value gets
        the same colour in every panel drawn with the same `values`. Default: the values
        present in `labels`.
    names : dict of int to str, optional
        The labels' names: a legend entry reads ``"3 (hippocampus)"``; default the values.

    Returns
    -------
    handles : list of matplotlib Patch
        The legend's entries, one per nonzero value present in `labels`, in increasing
        order (empty without labels).
    title : str
        The legend's title.
    """
    from matplotlib import colormaps
    from matplotlib.patches import Patch

    lab = np.asarray(labels)
    edge = np.zeros(lab.shape, bool)
    edge[1:, :] |= lab[1:, :] != lab[:-1, :]
    edge[:-1, :] |= lab[:-1, :] != lab[1:, :]
    edge[:, 1:] |= lab[:, 1:] != lab[:, :-1]
    edge[:, :-1] |= lab[:, :-1] != lab[:, 1:]
    edge &= lab != 0
    present = [int(v) for v in np.unique(lab) if v != 0]
    # colours are keyed by the position of a value among all of the figure's values, so that
    # a label keeps its colour in every panel even where another label is missing
    palette = sorted({int(v) for v in values if v != 0} | set(present)) if values else present
    overlay = np.zeros((*lab.shape, 4))
    if len(palette) <= LEGEND_LABELS:
        if len(palette) <= 9:  # tab10 without its grey
            colors = [c for i, c in enumerate(colormaps["tab10"].colors) if i != 7]
        else:
            colors = [c for i, c in enumerate(colormaps["tab20"].colors) if i not in (14, 15)]
        handles = []
        for v in present:
            color = (*colors[palette.index(v)], 1.0)
            overlay[edge & (lab == v)] = color
            handles.append(Patch(color=color, label=label_text(v, names)))
        title = "label value"
    else:
        overlay[edge] = (1.0, 0.85, 0.0, 1.0)
        handles = [Patch(color=(1.0, 0.85, 0.0), label=f"{len(present)} labels")] if present else []
        title = f"labels {present[0]}..{present[-1]}" if present else "label value"
    ax.imshow(overlay, origin="lower", aspect=aspect, interpolation="nearest")
    if handles and legend:
        ax.legend(
            handles=handles,
            title=title,
            fontsize=fontsize,
            title_fontsize=fontsize,
            loc="upper left",
            bbox_to_anchor=(1.01, 1.0),
            borderaxespad=0.0,
            handlelength=1.0,
            ncol=1 if len(handles) <= 10 else 2,
        )
    return handles, title


def bars_hidden(ax, half_lengths, *, markersize: float = 6.0, axis: str = "y") -> bool:
    """Whether error bars of these half-lengths would all hide behind their markers.

    Call once everything is drawn (the axis limits are final). A bar shows only where it
    reaches past the marker, whose radius is ``markersize / 2`` points.

    Parameters
    ----------
    ax : matplotlib Axes
    half_lengths : array_like
        Each bar's half-length, in data units of `axis` (for an asymmetric bar, the longer
        side); NaN is ignored.
    markersize : float
        Marker diameter in points (matplotlib's ``markersize``).
    axis : {"y", "x"}

    Returns
    -------
    bool
        True when no bar reaches past its marker (also when there is no bar).
    """
    lengths = np.asarray(half_lengths, float)
    lengths = lengths[np.isfinite(lengths)]
    if not lengths.size:
        return True
    lo, hi = ax.get_ylim() if axis == "y" else ax.get_xlim()
    box = ax.get_position()
    fig_in = ax.figure.get_figheight() if axis == "y" else ax.figure.get_figwidth()
    points = (box.height if axis == "y" else box.width) * fig_in * 72.0
    if ax.get_yscale() == "log" if axis == "y" else ax.get_xscale() == "log":
        return False  # no single data-per-point scale; do not claim the bars are hidden
    radius = 0.5 * markersize * abs(hi - lo) / points  # in data units
    return bool(lengths.max() < radius)


#: The words a figure uses for Monte-Carlo error bars that do not show.
HIDDEN_BARS = "smaller than the markers"


def wrap_name(name: str, width: int = 24) -> str:
    """`name` broken into lines of at most about `width` characters after ``_``, so that
    long registration names (a sweep's settings) do not run into their neighbours."""
    lines, line = [], ""
    for part in name.split("_"):
        piece = part if not line else "_" + part
        if line and len(line) + len(piece) > width:
            lines.append(line + "_")
            line = part
        else:
            line += piece
    return "\n".join([*lines, line])
