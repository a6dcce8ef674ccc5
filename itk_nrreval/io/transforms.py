"""Reading, chaining, inverting and checking registration transforms (SimpleITK at the edge).

Conventions
-----------
* Every transform maps **reference (fixed) points to image (moving) points**, in physical
  coordinates (mm, LPS), as ITK, SimpleITK, ANTs and elastix write them: an image is
  resampled onto the reference grid by looking up, for each reference voxel centre p, the
  image value at T(p).
* A **chain** is listed in the order ANTs reports ``fwdtransforms``: the first listed acts
  first. ``[s00_1Warp.nii.gz, s00_0GenericAffine.mat]`` maps a reference point p to the
  image point ``affine(warp(p))``. ``sitk.CompositeTransform`` applies the *last* transform
  of its list first, so it is given the reversed list (:func:`chain_transform` does this).
* Displacement fields are vector images whose vectors are physical displacements (mm) with
  components in ITK (x, y[, z]) order; ``sitk.GetArrayFromImage`` gives them as numpy
  arrays of shape ``(*spatial_zyx, dim)``. ANTs ``*1Warp.nii.gz`` files are 5D NIfTI
  ``(X, Y, Z, 1, 3)``; SimpleITK reads them as 3D images of 3-vectors (float32), which are
  cast to float64 here. A displacement field is always interpolated linearly.

Where things are
----------------
This module is the public face of the transform code, and checks transforms for folding
(:func:`jacobian_determinant`, :func:`folded_fraction`). Reading, writing, in-memory
transforms and chains are in :mod:`itk_nrreval.io._transform_io`; sampling displacements on a
grid in :mod:`itk_nrreval.io._displacements` (its compiled kernels in
:mod:`itk_nrreval.io._field_kernels`); inversion in :mod:`itk_nrreval.io._transform_inversion`.
Every name of :data:`__all__` is importable from here.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numba
import numpy as np
import SimpleITK as sitk

from ._displacements import (
    PointMap,
    displacement_after,
    displacement_array,
    displacement_field,
    has_only_fields,
    is_linear,
)
from ._images import Geometry
from ._transform_inversion import (
    INVERSION_STOPPING,
    PointwiseInverse,
    composed_displacement,
    invert,
)
from ._transform_io import (
    FIELD_SUFFIXES,
    TRANSFORM_SUFFIXES,
    InMemoryTransform,
    TransformPieces,
    chain_transform,
    field_components_problem,
    field_transform,
    file_stem,
    file_suffix,
    flatten,
    leaves,
    read_transform,
    to_sitk_transform,
    transform_digest,
    transform_pieces,
    write_transform,
)

__all__ = [
    "TRANSFORM_SUFFIXES",
    "FIELD_SUFFIXES",
    "InMemoryTransform",
    "to_sitk_transform",
    "transform_digest",
    "read_transform",
    "file_stem",
    "file_suffix",
    "leaves",
    "chain_transform",
    "TransformPieces",
    "transform_pieces",
    "flatten",
    "write_transform",
    "field_transform",
    "displacement_field",
    "invert",
    "INVERSION_STOPPING",
    "PointwiseInverse",
    "composed_displacement",
    "displacement_after",
    "displacement_array",
    "PointMap",
    "has_only_fields",
    "is_linear",
    "jacobian_determinant",
    "folded_fraction",
    "field_components_problem",
]


def jacobian_determinant(
    displacement: np.ndarray, *, spacing: Sequence[float], direction: Sequence[float] | None = None
) -> np.ndarray:
    """Jacobian determinant of ``p -> p + u(p)`` from a sampled displacement field.

    Parameters
    ----------
    displacement : ndarray of shape (*spatial, dim)
        Displacements in mm, numpy axis order for ``spatial`` ((z, y, x) in 3D) and ITK
        (x, y[, z]) order for the last axis -- what ``sitk.GetArrayFromImage`` gives.
    spacing : sequence of float, length dim
        Voxel size in mm along ITK (x, y[, z]).
    direction : sequence of float, length dim * dim, optional
        Row-major direction cosines (default identity).

    Returns
    -------
    ndarray of shape (*spatial,)
        ``det(I + du/dx)`` with derivatives in physical coordinates (central differences
        inside, one-sided at the border). Values <= 0 mark folded voxels; 1 is volume
        preserving.
    """
    u = np.asarray(displacement, dtype=np.float64)
    dim = u.shape[-1]
    if u.ndim != dim + 1 or dim not in (2, 3):
        raise ValueError(
            f"displacement: expected shape (*spatial, dim) with {dim} spatial axes, got {u.shape}"
        )
    spacing = np.asarray(spacing, dtype=np.float64)
    d = np.eye(dim) if direction is None else np.asarray(direction, np.float64).reshape(dim, dim)
    # physical x = origin + D @ diag(spacing) @ index  =>  d index / d x = (D diag(s))^-1
    index_per_mm = np.linalg.inv(d @ np.diag(spacing))
    det = np.empty(u.shape[:-1])
    # one compiled pass (no (n, dim, dim) temporaries); a 2D field as one plane of 3D
    _jacobian_determinant(u if dim == 3 else u[None], index_per_mm, det if dim == 3 else det[None])
    return det


@numba.njit(cache=True, inline="always")
def _difference_ends(at, n):  # pragma: no cover - compiled
    """The nodes a derivative along an axis of `n` nodes differences at node `at`, and the
    factor on their difference: np.gradient's (central, 1/2, inside; one-sided, 1, at the
    border; 0 on an axis of one node)."""
    if n == 1:
        return 0, 0, 0.0
    if at == 0:
        return 0, 1, 1.0
    if at == n - 1:
        return n - 2, n - 1, 1.0
    return at - 1, at + 1, 0.5


@numba.njit(cache=True, inline="always")
def _scaled(diff, factor):  # pragma: no cover - compiled
    """`diff` times a factor of :func:`_difference_ends` (a halving as a division, so
    that it rounds as np.gradient's does)."""
    if factor == 0.5:
        return diff / 2.0
    return diff if factor == 1.0 else 0.0


@numba.njit(cache=True, parallel=True)
def _jacobian_determinant(u, m, out):  # pragma: no cover - compiled
    """``out = det(I + G @ m)`` with ``G[c, a] = d u_c / d index_a`` of a field `u`
    (nz, ny, nx, d), d 2 or 3 (a 2D field as nz = 1), `m` (d, d) index steps per mm.
    Slices run in parallel; every voxel is computed alone, so the numbers do not depend on
    the number of threads. Written out for d = 3 and d = 2 (a loop over the 3 x 3 entries
    costs three times as much at 1 mm)."""
    nz, ny, nx, d = u.shape
    for slice_ in numba.prange(nz):
        k = np.int64(slice_)  # prange's index is unsigned
        zl, zh, zf = _difference_ends(k, nz)
        for j in range(ny):
            yl, yh, yf = _difference_ends(j, ny)
            for i in range(nx):
                xl, xh, xf = _difference_ends(i, nx)
                # g_ca: d u_c / d index a (x, y, z)
                g00 = _scaled(u[k, j, xh, 0] - u[k, j, xl, 0], xf)
                g10 = _scaled(u[k, j, xh, 1] - u[k, j, xl, 1], xf)
                g01 = _scaled(u[k, yh, i, 0] - u[k, yl, i, 0], yf)
                g11 = _scaled(u[k, yh, i, 1] - u[k, yl, i, 1], yf)
                if d == 2:
                    j00 = (0.0 + g00 * m[0, 0] + g01 * m[1, 0]) + 1.0
                    j01 = 0.0 + g00 * m[0, 1] + g01 * m[1, 1]
                    j10 = 0.0 + g10 * m[0, 0] + g11 * m[1, 0]
                    j11 = (0.0 + g10 * m[0, 1] + g11 * m[1, 1]) + 1.0
                    out[k, j, i] = j00 * j11 - j01 * j10
                    continue
                g20 = _scaled(u[k, j, xh, 2] - u[k, j, xl, 2], xf)
                g21 = _scaled(u[k, yh, i, 2] - u[k, yl, i, 2], yf)
                g02 = _scaled(u[zh, j, i, 0] - u[zl, j, i, 0], zf)
                g12 = _scaled(u[zh, j, i, 1] - u[zl, j, i, 1], zf)
                g22 = _scaled(u[zh, j, i, 2] - u[zl, j, i, 2], zf)
                # J = I + G m, each entry summed from 0 in the order a = x, y, z
                j00 = (0.0 + g00 * m[0, 0] + g01 * m[1, 0] + g02 * m[2, 0]) + 1.0
                j01 = 0.0 + g00 * m[0, 1] + g01 * m[1, 1] + g02 * m[2, 1]
                j02 = 0.0 + g00 * m[0, 2] + g01 * m[1, 2] + g02 * m[2, 2]
                j10 = 0.0 + g10 * m[0, 0] + g11 * m[1, 0] + g12 * m[2, 0]
                j11 = (0.0 + g10 * m[0, 1] + g11 * m[1, 1] + g12 * m[2, 1]) + 1.0
                j12 = 0.0 + g10 * m[0, 2] + g11 * m[1, 2] + g12 * m[2, 2]
                j20 = 0.0 + g20 * m[0, 0] + g21 * m[1, 0] + g22 * m[2, 0]
                j21 = 0.0 + g20 * m[0, 1] + g21 * m[1, 1] + g22 * m[2, 1]
                j22 = (0.0 + g20 * m[0, 2] + g21 * m[1, 2] + g22 * m[2, 2]) + 1.0
                out[k, j, i] = (
                    j00 * (j11 * j22 - j12 * j21)
                    - j01 * (j10 * j22 - j12 * j20)
                    + j02 * (j10 * j21 - j11 * j20)
                )


def folded_fraction(
    transform: sitk.Transform | str | os.PathLike | Sequence,
    reference: sitk.Image | Geometry,
    *,
    mask: np.ndarray | None = None,
) -> float:
    """Fraction of the reference grid's voxels where `transform` folds (Jacobian det <= 0).

    Parameters
    ----------
    transform : sitk.Transform, path or chain (ANTs order)
    reference : sitk.Image or Geometry
        The grid the Jacobian is sampled on.
    mask : ndarray of bool, numpy shape of the grid, optional
        Count only these voxels.

    Returns
    -------
    float
        In [0, 1]; 0 for a transform that is invertible everywhere on the grid.
    """
    g = reference if isinstance(reference, Geometry) else Geometry.from_image(reference)
    field = displacement_field(chain_transform(transform), g)
    det = jacobian_determinant(
        sitk.GetArrayViewFromImage(field), spacing=g.spacing, direction=g.direction
    )
    folded = det <= 0
    if mask is not None:
        folded = folded[np.asarray(mask, bool)]
    return float(folded.mean()) if folded.size else 0.0
