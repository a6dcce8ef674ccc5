"""A montage PNG of a population: images in a grid with their label contours."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

import numpy as np
import SimpleITK as sitk

__all__ = ["save_montage", "label_boundaries"]


def label_boundaries(labels: np.ndarray) -> np.ndarray:
    """Boolean map of the pixels of a 2D label map that touch a different label (4-connected).

    Parameters
    ----------
    labels : ndarray of int, shape (rows, cols)

    Returns
    -------
    ndarray of bool, shape (rows, cols)
        True on nonzero-label pixels next to another value: the label contours, one pixel thick.
    """
    labels = np.asarray(labels)
    edge = np.zeros(labels.shape, dtype=bool)
    edge[1:, :] |= labels[1:, :] != labels[:-1, :]
    edge[:-1, :] |= labels[:-1, :] != labels[1:, :]
    edge[:, 1:] |= labels[:, 1:] != labels[:, :-1]
    edge[:, :-1] |= labels[:, :-1] != labels[:, 1:]
    return edge & (labels != 0)


def _plane(image: sitk.Image, axial_index: int | None) -> np.ndarray:
    """The image as a 2D array (rows = y, cols = x); a 3D image gives one axial plane."""
    arr = sitk.GetArrayFromImage(image)
    if arr.ndim == 3:
        k = arr.shape[0] // 2 if axial_index is None else int(axial_index)
        if not 0 <= k < arr.shape[0]:
            raise ValueError(f"axial_index must be in [0, {arr.shape[0]}), got {axial_index!r}")
        arr = arr[k]
    return arr


def save_montage(
    images: Sequence[sitk.Image],
    labels: Sequence[sitk.Image] | None = None,
    *,
    path: str | os.PathLike,
    titles: Sequence[str] | None = None,
    ncols: int | None = None,
    axial_index: int | None = None,
    max_images: int = 36,
    panel_inches: float = 1.6,
    dpi: int = 100,
) -> None:
    """Write a montage of images (grey) with label contours (coloured) to a PNG file.

    Parameters
    ----------
    images : sequence of sitk.Image
        2D images, or 3D images of which the axial plane `axial_index` (numpy axis 0, i.e.
        ITK z index; default the middle) is shown. Rows of the panel are y, columns x, as
        stored (the origin at the top left). Each image is scaled to its own 1st-99th percentile.
    labels : sequence of sitk.Image, optional
        Integer label maps on the images' grids; their boundaries are drawn, one colour per
        label value.
    path : path-like
        Output PNG, written atomically.
    titles : sequence of str, optional
        One caption per panel.
    ncols : int, optional
        Panels per row (default: about square).
    max_images : int
        Show only the first `max_images`.
    panel_inches, dpi
        Size of one panel (inches) and resolution.
    """
    import matplotlib
    from matplotlib.figure import Figure  # no pyplot: the process's backend is left alone

    from itk_nrreval._output import atomic_path

    n = min(len(images), max_images)
    if n == 0:
        raise ValueError("images is empty: nothing to draw")
    if labels is not None and len(labels) < n:
        raise ValueError(f"labels has {len(labels)} entries, expected one per image ({n})")
    ncols = ncols or int(math.ceil(math.sqrt(n)))
    nrows = int(math.ceil(n / ncols))
    fig = Figure(figsize=(ncols * panel_inches, nrows * panel_inches), dpi=dpi)
    cmap = matplotlib.colormaps["tab20"]
    for i in range(n):
        ax = fig.add_axes(((i % ncols) / ncols, 1 - (i // ncols + 1) / nrows, 1 / ncols, 1 / nrows))
        ax.set_axis_off()
        img = _plane(images[i], axial_index).astype(np.float64)
        lo, hi = np.percentile(img, [1, 99])
        rgb = np.repeat(np.clip((img - lo) / max(hi - lo, 1e-12), 0, 1)[..., None], 3, axis=-1)
        if labels is not None:
            lab = _plane(labels[i], axial_index).astype(np.int64)
            edge = label_boundaries(lab)
            colours = np.asarray(cmap(lab % 20))[..., :3]
            rgb[edge] = colours[edge]
        ax.imshow(rgb, interpolation="nearest", aspect="equal")
        if titles is not None and i < len(titles):
            ax.text(2, 2, titles[i], color="yellow", fontsize=7, va="top", ha="left")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", facecolor="black")
