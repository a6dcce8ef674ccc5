"""The affine map closest to a transform on a grid, by least squares over its voxels: the fit
(:class:`AffineFit`, :func:`affine_fit`) and its normal equations, accumulated slab by slab by
a compiled kernel (:class:`AffineSums`).

:func:`affine_fit` samples a transform and fits it (:mod:`itk_nrreval.io.plausibility` exports
it); :func:`itk_nrreval.io.plausibility.deformation_measures` fits from the sampling it makes
anyway. The notes of :func:`affine_fit` give the formulas.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass

import numba
import numpy as np
import SimpleITK as sitk

from .._errors import InputError
from .._output import json_number
from ._grid_slabs import SLAB_VOXELS, as_geometry, slabs
from ._images import Geometry
from .transforms import displacement_array, flatten, has_only_fields, transform_pieces

__all__ = ["AffineFit", "AffineSums", "NAN_FIT", "affine_fit"]


@dataclass(frozen=True)
class AffineFit:
    """The affine map closest to a transform on a grid (least squares over its voxels).

    Attributes
    ----------
    linear_det : float
        Determinant of the fitted map's linear part (unitless): about 1 for a pose, negative
        for a map that mirrors space (axes flipped).
    displacement_rms_mm : float
        Root mean square of ``|T(p) - p|`` over the evaluated voxels, mm.
    nonlinear_rms_mm : float
        Root mean square of ``|T(p) - (A p + b)|``, mm, with ``A p + b`` the fitted affine
        map: the part of the displacement no affine map explains; 0 (to round-off) for a
        linear transform.
    """

    linear_det: float
    displacement_rms_mm: float
    nonlinear_rms_mm: float

    def to_dict(self) -> dict:
        return {k: json_number(v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: Mapping) -> AffineFit:
        """Inverse of :meth:`to_dict` (None back to NaN)."""
        return cls(**{k: math.nan if data[k] is None else float(data[k]) for k in asdict(NAN_FIT)})


class AffineSums:
    """The normal equations of :func:`affine_fit` (see its notes),
    accumulated slab by slab over the grid `g`: ``S_qq``, ``S_qu``, ``sum |u|^2`` and the voxel
    count."""

    def __init__(self, g: Geometry):
        d = g.dimension
        self.direction = np.asarray(g.direction, np.float64).reshape(d, d)
        self.spacing = np.asarray(g.spacing, np.float64)
        size = np.asarray(g.size)
        self.centre = np.asarray(g.origin) + self.direction @ (self.spacing * (size - 1) / 2)
        self.s_qq = np.zeros((d + 1, d + 1))
        self.s_qu = np.zeros((d + 1, d))
        self.s_uu = 0.0
        self.count = 0

    def add(self, u: np.ndarray, slab_grid: Geometry, sel: np.ndarray | None) -> None:
        """Add one slab: `u` its displacement (mm, shape ``(*slab_grid.shape, d)``), `sel` its
        evaluated voxels (bool, ``slab_grid.shape``) or None for all."""
        d = len(self.spacing)
        u = np.asarray(u, np.float64)
        # q of voxel index x (ITK order): (origin - centre) + step @ x
        step = self.direction * self.spacing
        start = np.asarray(slab_grid.origin) - self.centre
        if d == 2:  # one plane of 3D
            u, sel = u[None], None if sel is None else np.asarray(sel)[None]
        every = sel is None
        sel = np.ones((1, 1, 1), bool) if every else np.asarray(sel, bool)
        # per slice of the slab (compiled, in parallel), then added up in slice order: the
        # numbers do not depend on the number of threads
        parts = np.zeros((u.shape[0], d + 1, 2 * d + 2))  # [S_qq | S_qu | sum |u|^2]
        _affine_sums(u, sel, every, start, step, parts)
        total = parts.sum(axis=0)
        self.s_qq += total[:, : d + 1]
        self.s_qu += total[:, d + 1 : 2 * d + 1]
        self.s_uu += float(total[0, 2 * d + 1])
        self.count += int(round(total[d, d]))  # the sum of 1 * 1 over the voxels

    def fit(self) -> AffineFit:
        d = len(self.spacing)
        if self.count <= d or np.linalg.matrix_rank(self.s_qq) < d + 1:
            return NAN_FIT
        b = np.linalg.solve(self.s_qq, self.s_qu)
        residual = max(self.s_uu - float(np.sum(b * self.s_qu)), 0.0)
        return AffineFit(
            linear_det=float(np.linalg.det(np.eye(d) + b[:d].T)),
            displacement_rms_mm=math.sqrt(self.s_uu / self.count),
            nonlinear_rms_mm=math.sqrt(residual / self.count),
        )


@numba.njit(cache=True, parallel=True)
def _affine_sums(u, sel, every, start, step, parts):  # pragma: no cover - compiled
    """For each slice k of `u` (nz, ny, nx, d; d 2 or 3, a 2D slab as nz = 1): with
    ``q1 = [start + step @ (i, j[, k]), 1]`` at every voxel selected by `sel` (all when
    `every`), ``parts[k, :, :d+1] = sum q1 q1^T``, ``parts[k, :, d+1:2d+1] = sum q1 u^T`` and
    ``parts[k, 0, 2d+1] = sum |u|^2``.

    Along a row (j, k fixed) ``q1 = a + i s`` with ``a = q1`` at i = 0 and ``s = [step[:, 0],
    0]``, so a row adds ``n a a^T + (a s^T + s a^T) sum i + s s^T sum i^2`` and
    ``a (sum u)^T + s (sum i u)^T``: a voxel costs its sums, not the outer products."""
    nz, ny, nx, d = u.shape
    for slice_ in numba.prange(nz):
        k = np.int64(slice_)  # prange's index is unsigned
        a = np.ones(d + 1)
        s = np.zeros(d + 1)
        for r in range(d):
            s[r] = step[r, 0]
        su = np.empty(d)
        siu = np.empty(d)
        acc = parts[k]
        for j in range(ny):
            for r in range(d):
                q = start[r] + step[r, 1] * j
                if d == 3:
                    q += step[r, 2] * k
                a[r] = q
            n = si = sii = suu = 0.0
            su[:] = 0.0
            siu[:] = 0.0
            for i in range(nx):
                if not every and not sel[k, j, i]:
                    continue
                x = np.float64(i)
                n += 1.0
                si += x
                sii += x * x
                for c in range(d):
                    v = u[k, j, i, c]
                    su[c] += v
                    siu[c] += x * v
                    suu += v * v
            if n == 0.0:
                continue
            for r in range(d + 1):
                for c in range(d + 1):
                    acc[r, c] += (
                        n * a[r] * a[c] + (a[r] * s[c] + s[r] * a[c]) * si + s[r] * s[c] * sii
                    )
                for c in range(d):
                    acc[r, d + 1 + c] += a[r] * su[c] + s[r] * siu[c]
            acc[0, 2 * d + 1] += suu


#: The fit of a transform whose voxels determine no affine map.
NAN_FIT = AffineFit(math.nan, math.nan, math.nan)


def affine_fit(
    transform: sitk.Transform,
    grid: Geometry | sitk.Image,
    *,
    mask: np.ndarray | None = None,
    max_slab_voxels: int = SLAB_VOXELS,
) -> AffineFit:
    """Fit an affine map to a transform over a grid's voxels, by least squares.

    Parameters
    ----------
    transform : sitk.Transform (or a path / chain in ANTs order, or its TransformPieces)
        Maps reference points to image points (mm, LPS). Linear maps and displacement
        fields are sampled by the compiled kernels (to about 1e-13 mm of ITK's sampling),
        other pieces by ITK.
    grid : Geometry or sitk.Image
        The points p (voxel centres): the registration's reference grid.
    mask : ndarray of bool, shape ``grid.shape`` (numpy order), optional
        Fit over these voxels only (at least ``dimension + 1`` of them, not all on one plane).
    max_slab_voxels : int
        Sample the displacement slab by slab along the last axis above this many voxels, so
        that memory stays bounded; the result does not depend on it.

    Returns
    -------
    AffineFit
        All NaN when the voxels do not determine an affine map (too few, or on one plane).

    Notes
    -----
    With ``u(p) = T(p) - p`` and ``q = p - c`` (c the grid's centre, so that the sums do not
    lose the millimetres to the coordinates' size), the fit ``u ~ B^T [q, 1]`` solves the
    normal equations ``S_qq B = S_qu`` with ``S_qq = sum [q, 1][q, 1]^T`` and
    ``S_qu = sum [q, 1] u^T``, accumulated slab by slab; the linear part is ``I + B[:d]^T``
    and the residual sum of squares ``sum |u|^2 - <B, S_qu>``.
    """
    g = as_geometry(grid)
    pieces = transform_pieces(transform)  # read and taken apart once, for every slab
    dim = pieces[0].GetDimension()
    if dim != g.dimension:
        raise InputError(f"transform: {dim}D transform on a {g.dimension}D grid {g.size}")
    # linear maps and fields are sampled by the compiled kernels; anything else by ITK
    t = pieces if has_only_fields(pieces) else flatten(pieces)
    sums = AffineSums(g)
    for rows, _halo, slab_grid, _inner in slabs(g, max(int(max_slab_voxels), 1)):
        sums.add(displacement_array(t, slab_grid), slab_grid, None if mask is None else mask[rows])
    return sums.fit()
