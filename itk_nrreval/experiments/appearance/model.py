"""Full appearance-model diagnostics: the paper's Table 1 (Section III-B).

Why is specificity measured on the shape-free texture model and not on the full appearance
model? The paper's answer is one diagnostic: sample the full (shape + texture) appearance
model, and count how many samples fall in each training image's Voronoi cell in the space
of affinely aligned images, once for the raw training images and once for the training
images *projected* onto the model (their model reconstructions). Raw images that lie off the
model sub-manifold (representation error) may have cells the samples never reach.

The model of one registration (reference points -> image points, mm, LPS)
--------------------------------------------------------------------------
For each training image i with transform ``T_i`` on the registration's reference grid:

* **Affine part** ``A_i`` (:func:`affine_part`): the linear transforms of ``T_i``'s chain
  composed in chain order, the warps left out; when the chain has no linear transform (e.g.
  one elastix displacement field with the affine folded in), the least-squares affine fit to
  the dense map ``p -> T_i(p)`` over the grid's voxel centres.
* **Raw aligned image** ``R_i(q) = I_i(A_i(q))``: image i resampled onto the reference grid
  through ``A_i`` -- a point of the data space R^n of affinely aligned images.
* **Shape** ``u_i(p) = A_i^-1(T_i(p)) - p``: the displacement field (mm, ITK (x, y[, z])
  components) of the non-affine part, on the reference grid; ``phi_i(p) = p + u_i(p)`` maps
  reference points into the aligned space.
* **Texture** ``g_i(p) = I_i(T_i(p))``: the shape-free texture (image i resampled through
  its full transform), the images that :class:`~itk_nrreval.measures.model.TextureModel` models.

Then ``R_i(q) = g_i(phi_i^-1(q))``: the aligned image is its texture warped by its shape.
The model (:class:`AppearanceModel`, paper eqs. 1-2) is the shape PCA ``u = mean_u + P_s b_s``,
the texture PCA ``g = mean_g + P_g b_g``, and the combined PCA of the concatenated
parameters ``[W b_s, b_g] = Q c``. An instance ``c`` is synthesised in the aligned space as
``image(q) = g(phi^-1(q))`` with ``phi^-1`` from ``sitk.InvertDisplacementField``
(:func:`itk_nrreval.io.transforms.invert`) and linear interpolation (0 outside the grid).
Every mode is kept, so a training image's own parameters ``c_i`` give back ``u_i`` and
``g_i`` exactly; its *projection* ``synthesise(c_i)`` differs from ``R_i`` only by the
resampling and inversion losses: the representation error.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import SimpleITK as sitk

from ..._errors import InputError, readable
from ..._progress import progress_bar
from ...io._images import Geometry, read_image
from ...io.frame import read_chains, resample_images, resample_onto
from ...io.manifest import Manifest, load_manifest
from ...io.transforms import chain_transform, displacement_field, field_transform, flatten, invert
from ...measures import _search
from ...measures.model import TextureModel, centred_gram

__all__ = [
    "NEAR_EMPTY_FRACTION",
    "AppearanceModel",
    "CellPopulations",
    "AppearanceDiagnostics",
    "affine_part",
    "fit_appearance",
    "nearest_images",
    "appearance_diagnostics",
]

#: A cell is *near-empty* when it holds fewer than this fraction of the uniform share M / N.
NEAR_EMPTY_FRACTION = 0.1
# Largest number of voxel values held for one chunk of synthesised samples (32 MB of float64).
_CHUNK_VALUES = 1 << 22
_MAX_CHUNK = 64


# ----------------------------------------------------------------------------- geometry


def _grid_points(g: Geometry) -> np.ndarray:
    """Physical voxel centres (mm, LPS) of grid `g`: shape (n_voxels, dim), ITK (x, y[, z])
    components, voxels in numpy (C) order of the array shape (z, y, x)."""
    index = np.indices(g.shape).reshape(g.dimension, -1)[::-1].T  # ITK index order
    d = np.asarray(g.direction).reshape(g.dimension, g.dimension)
    return np.asarray(g.origin) + (index * np.asarray(g.spacing)) @ d.T


def _fit_affine(points: np.ndarray, mapped: np.ndarray) -> sitk.AffineTransform:
    """Least-squares affine ``x -> A (x - c) + c + t`` with ``mapped ~ A(points)``.

    points, mapped : ndarray of shape (n_points, dim), mm. The centre c is the points' mean
    (for conditioning); the fit is exact when `mapped` is an affine image of `points`.
    """
    dim = points.shape[1]
    centre = points.mean(axis=0)
    design = np.hstack([points - centre, np.ones((points.shape[0], 1))])
    coef, _, rank, _ = np.linalg.lstsq(design, mapped, rcond=None)
    if rank < dim + 1:
        raise InputError(
            "affine part: cannot fit an affine to a dense field on a grid with a single voxel "
            "along some axis; put an affine transform in the registration's chain"
        )
    affine = sitk.AffineTransform(dim)
    affine.SetCenter(tuple(float(v) for v in centre))
    affine.SetMatrix(tuple(float(v) for v in coef[:dim].T.ravel()))
    affine.SetTranslation(tuple(float(v) for v in coef[dim] - centre))
    return affine


def _corners(g: Geometry) -> Geometry:
    """The 2^dim corners of `g`'s extent (at least one voxel along each axis) as a tiny grid:
    affinely independent points on which a linear transform is fitted exactly."""
    spacing = tuple(sp * max(s - 1, 1) for sp, s in zip(g.spacing, g.size, strict=True))
    return Geometry((2,) * g.dimension, spacing, g.origin, g.direction)


def affine_part(
    transform: sitk.Transform, reference: sitk.Image | Geometry
) -> sitk.AffineTransform:
    """The affine part ``A`` of a registration transform (reference points -> image points).

    Parameters
    ----------
    transform : sitk.Transform
        ``T``: maps reference points (mm, LPS) to image points; a composite or a single
        transform.
    reference : sitk.Image or Geometry
        The reference grid (the registration's frame).

    Returns
    -------
    sitk.AffineTransform
        If ``T``'s flattened chain holds linear transforms (``AffineTransform``,
        ``Euler*``, ``Similarity*``, ``Translation``, ...), their composition in chain order
        with the non-linear ones left out (e.g. ``affine(warp(p))`` gives ``affine``).
        Otherwise the least-squares affine fit to ``p -> T(p)`` over every voxel centre p of
        the grid (a dense field with the affine folded in, as elastix writes it).

    Notes
    -----
    ``A^-1 o T`` is then the non-affine part; for ``T = A o W`` it is exactly ``W``.
    """
    g = reference if isinstance(reference, Geometry) else Geometry.from_image(reference)
    flat = flatten(transform)
    leaves = (
        [flat.GetNthTransform(i).Downcast() for i in range(flat.GetNumberOfTransforms())]
        if isinstance(flat, sitk.CompositeTransform)
        else [flat]
    )
    linear = [t for t in leaves if t.IsLinear()]
    if linear:
        # sitk list order (last acts first) is kept: the composite of the linear leaves alone.
        composed = linear[0] if len(linear) == 1 else sitk.CompositeTransform(linear)
        grid = _corners(g)
        target = composed
    else:
        grid = g
        target = transform
    points = _grid_points(grid)
    disp = sitk.GetArrayFromImage(displacement_field(target, grid)).reshape(-1, g.dimension)
    return _fit_affine(points, points + disp)


# ----------------------------------------------------------------------------- the model


def _pca(data: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """PCA of (n_items, n_values) data through :class:`TextureModel` (Gram matrix).

    Returns ``(mean (n_values,), modes (n_modes, n_values) orthonormal rows, params
    (n_items, n_modes))`` with ``data = mean + params @ modes``; zero modes when every item
    is the same.
    """
    n, m = data.shape
    mean = data.mean(axis=0)
    if not np.any(data != data[:1]):
        return mean, np.zeros((0, m)), np.zeros((n, 0))
    # a PCA of any items, not of a cohort's images: equal items (the reference subject's
    # identity field and another's) are legitimate here, so from_images' checks are not
    gram, mean_, _, _ = centred_gram(data)
    model = TextureModel.from_gram(gram, mean=mean_)
    params = model.training_params
    # unit mode k = X_c^T v_k / sqrt(lambda_k) = X_c^T b_k / lambda_k (lambda: Gram eigenvalue)
    gram_eig = model.mode_variances * (n - 1)
    modes = (params / gram_eig).T @ (data - model.mean)
    return model.mean, modes, params


def _fix_signs(vectors: np.ndarray) -> np.ndarray:
    """Make each column's largest-magnitude entry positive (reproducible across LAPACKs)."""
    if vectors.shape[1] == 0:
        return vectors
    rows = np.argmax(np.abs(vectors), axis=0)
    return vectors * np.sign(vectors[rows, np.arange(vectors.shape[1])])


@dataclass(frozen=True, eq=False)
class AppearanceModel:
    """A combined shape and texture model on one reference grid (paper eqs. 1-2).

    Build it with :meth:`from_fields`; draw parameters with :meth:`sample_params`; turn
    parameters into a shape and a texture with :meth:`instance`, or into an image of the
    affinely aligned space with :meth:`synthesise`.

    Attributes
    ----------
    geometry : Geometry
        The reference grid.
    shape_mean : ndarray of shape (*spatial, dim)
        Mean displacement field (mm, ITK (x, y[, z]) components, numpy spatial order).
    shape_modes : ndarray of shape (n_shape_modes, n_voxels * dim)
        Orthonormal shape modes ``P_s^T`` (flattened fields).
    texture_mean : ndarray of shape (*spatial,)
        Mean shape-free texture (intensity units).
    texture_modes : ndarray of shape (n_texture_modes, n_voxels)
        Orthonormal texture modes ``P_g^T``.
    shape_weight : float
        ``W`` in ``[W b_s, b_g]``: ``sqrt(total texture variance / total shape variance)``
        (intensity units per mm), so that shape and texture carry equal total variance in
        the combined model; 1 when either has no variation.
    combined_modes : ndarray of shape (n_shape_modes + n_texture_modes, n_combined_modes)
        Orthonormal columns ``Q``: ``[W b_s, b_g] = Q c``.
    combined_variances : ndarray of shape (n_combined_modes,)
        Variance of ``c`` along each mode (divided by N - 1), decreasing.
    training_params : ndarray of shape (n_images, n_combined_modes)
        ``c_i`` of the training images (every mode kept: they reproduce ``u_i``, ``g_i``).
    """

    geometry: Geometry
    shape_mean: np.ndarray = field(repr=False)
    shape_modes: np.ndarray = field(repr=False)
    texture_mean: np.ndarray = field(repr=False)
    texture_modes: np.ndarray = field(repr=False)
    shape_weight: float
    combined_modes: np.ndarray = field(repr=False)
    combined_variances: np.ndarray = field(repr=False)
    training_params: np.ndarray = field(repr=False)

    @property
    def n_images(self) -> int:
        return self.training_params.shape[0]

    @property
    def n_shape_modes(self) -> int:
        return self.shape_modes.shape[0]

    @property
    def n_texture_modes(self) -> int:
        return self.texture_modes.shape[0]

    @property
    def n_modes(self) -> int:
        """Number of combined modes."""
        return self.training_params.shape[1]

    @classmethod
    def from_fields(
        cls, displacements: np.ndarray, textures: np.ndarray, *, geometry: Geometry
    ) -> AppearanceModel:
        """Fit the model to N shapes and shape-free textures on one grid.

        Parameters
        ----------
        displacements : ndarray of shape (n_images, *spatial, dim)
            ``u_i(p) = A_i^-1(T_i(p)) - p`` in mm, numpy spatial order (z, y, x), vector
            components in ITK (x, y[, z]) order (as ``sitk.GetArrayFromImage`` gives them).
        textures : ndarray of shape (n_images, *spatial)
            Shape-free textures ``g_i`` on the same grid.
        geometry : Geometry
            The grid; its ``shape`` must equal ``spatial``.

        Raises
        ------
        InputError
            Fewer than 3 images, mismatched shapes, or neither shape nor texture varies.
        """
        u = np.asarray(displacements, dtype=np.float64)
        g = np.asarray(textures, dtype=np.float64)
        n = g.shape[0]
        if n < 3:
            raise InputError(f"need at least 3 images to build an appearance model, got {n}")
        if g.shape[1:] != geometry.shape or u.shape != (n, *geometry.shape, geometry.dimension):
            raise InputError(
                f"appearance model: textures {g.shape} and displacements {u.shape} do not match "
                f"{n} images on a grid of numpy shape {geometry.shape}"
            )
        shape_mean, shape_modes, b_s = _pca(u.reshape(n, -1))
        texture_mean, texture_modes, b_g = _pca(g.reshape(n, -1))
        if b_s.shape[1] + b_g.shape[1] == 0:
            raise InputError("appearance model: all shapes and textures are identical")
        var_s, var_g = float(np.sum(b_s**2)), float(np.sum(b_g**2))
        weight = math.sqrt(var_g / var_s) if var_s > 0 and var_g > 0 else 1.0
        joint = np.hstack([weight * b_s, b_g])  # centred: PCA parameters have zero mean
        left, sv, right_t = np.linalg.svd(joint, full_matrices=False)
        keep = sv > sv[0] * max(joint.shape) * 1e-12
        q = _fix_signs(right_t[keep].T)
        return cls(
            geometry=geometry,
            shape_mean=shape_mean.reshape(*geometry.shape, geometry.dimension),
            shape_modes=shape_modes,
            texture_mean=texture_mean.reshape(geometry.shape),
            texture_modes=texture_modes,
            shape_weight=weight,
            combined_modes=q,
            combined_variances=sv[keep] ** 2 / (n - 1),
            training_params=joint @ q,
        )

    def sample_params(self, seed: int, start: int, stop: int) -> np.ndarray:
        """Parameters ``c`` of model samples ``start:stop``: shape (stop - start, n_modes).

        ``c_k = z(seed, mu, k) sqrt(combined_variances[k])`` with the counter-based standard
        normals of :mod:`itk_nrreval.measures._search.sampling`: sample ``mu`` is the same whatever
        the chunk it is drawn in.
        """
        z = _search.sampling.standard_normals(int(seed), int(start), int(stop), self.n_modes)
        return z * np.sqrt(self.combined_variances)

    def instance(self, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Shape and texture of combined parameters `params` (shape (n_modes,)).

        Returns
        -------
        displacement : ndarray of shape (*spatial, dim)
            mm, ITK (x, y[, z]) components.
        texture : ndarray of shape (*spatial,)
        """
        joint = self.combined_modes @ np.asarray(params, dtype=np.float64)
        b_s = joint[: self.n_shape_modes] / self.shape_weight
        b_g = joint[self.n_shape_modes :]
        u = self.shape_mean + (b_s @ self.shape_modes).reshape(self.shape_mean.shape)
        g = self.texture_mean + (b_g @ self.texture_modes).reshape(self.texture_mean.shape)
        return u, g

    def synthesise(
        self,
        params: np.ndarray,
        *,
        max_iterations: int = 20,
        max_error: float = 0.01,
        mean_error: float = 1e-4,
    ) -> np.ndarray:
        """The image of `params` in the affinely aligned space: ``g(phi^-1(q))``.

        Parameters
        ----------
        params : ndarray of shape (n_modes,)
        max_iterations, max_error, mean_error
            Passed to :func:`itk_nrreval.io.transforms.invert` (``sitk.InvertDisplacementField``).
            20 fixed-point iterations leave a round-trip residual ``|phi(phi^-1(q)) - q|``
            of about 1e-3 mm for smooth fields of a few mm (measured; 50 iterations reach
            round-off at 2-5 times the cost, which dominates the run time).

        Returns
        -------
        ndarray of shape (*spatial,)
            The texture resampled (linear, 0 outside the grid) through ``phi^-1``, where
            ``phi(p) = p + u(p)``. A zero displacement returns the texture unchanged.
        """
        u, g = self.instance(params)
        if not u.any():
            return g
        grid = self.geometry
        warp = grid.apply_to(sitk.GetImageFromArray(u, isVector=True))
        inverse = invert(
            field_transform(warp),
            max_iterations=max_iterations,
            max_error=max_error,
            mean_error=mean_error,
        )
        texture = grid.apply_to(sitk.GetImageFromArray(np.asarray(g, dtype=np.float64)))
        out = resample_onto(texture, inverse, grid, sitk.sitkLinear)
        return sitk.GetArrayFromImage(out)


def _load(source) -> Manifest:
    if isinstance(source, Manifest):
        return source
    if isinstance(source, (str, os.PathLike, Mapping)):
        return load_manifest(source)
    raise InputError(
        f"manifest: expected a path, a dict or a Manifest, got {type(source).__name__}"
    )


def _check_registration(manifest: Manifest, registration) -> str:
    if registration not in manifest.registrations:
        raise InputError(
            f"registration {registration!r} is not in the manifest "
            f"(have: {', '.join(manifest.names)})"
        )
    return registration


def fit_appearance(
    manifest_or_dict, *, registration: str, progress: bool = True
) -> tuple[AppearanceModel, np.ndarray]:
    """The appearance model of one registration and the raw affinely aligned images.

    Parameters
    ----------
    manifest_or_dict : path, dict or Manifest
        See :func:`itk_nrreval.load_manifest`.
    registration : str
        A registration of the manifest; its reference image's grid is the model's grid.
    progress : bool
        Progress bars on stderr.

    Returns
    -------
    model : AppearanceModel
    raw : ndarray of shape (n_images, *spatial)
        ``R_i``: each image resampled (linear, 0 outside) through :func:`affine_part` of its
        transform onto the reference grid.
    """
    manifest = _load(manifest_or_dict)
    name = _check_registration(manifest, registration)
    reference = read_image(manifest.registrations[name].reference, what="reference image")
    grid = Geometry.from_image(reference)
    chains = read_chains(manifest, name)
    affines = [affine_part(t, grid) for t in chains]
    raw = resample_images(
        manifest.scored_images, affines, grid, progress=progress, desc=f"{name}: affine"
    )
    textures = resample_images(
        manifest.scored_images, chains, grid, progress=progress, desc=f"{name}: texture"
    )
    fields = np.stack(
        [
            sitk.GetArrayFromImage(
                displacement_field(chain_transform([t, a.GetInverse()]), grid)  # A^-1(T(p))
            )
            for t, a in zip(chains, affines, strict=True)
        ]
    )
    return AppearanceModel.from_fields(fields, textures, geometry=grid), raw


# ----------------------------------------------------------------------------- diagnostics


def nearest_images(
    samples: np.ndarray, training: np.ndarray, *, training_sq: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest training image (L2 in image space) of each sample, with BLAS.

    Parameters
    ----------
    samples : ndarray of shape (n_samples, n_voxels)
    training : ndarray of shape (n_images, n_voxels)
    training_sq : ndarray of shape (n_images,), optional
        ``|x_i|^2`` when already known.

    Returns
    -------
    distance : ndarray of shape (n_samples,)
        ``min_i |y - x_i|_2`` (intensity units), recomputed directly for the nearest image.
    index : ndarray of int, shape (n_samples,)
        The nearest training image (the first on ties).

    Notes
    -----
    The search uses ``|y - x|^2 = |y|^2 - 2 y.x + |x|^2`` (one matrix product); memory is
    O(n_samples (n_images + n_voxels)), so callers pass samples in chunks.
    """
    y = np.asarray(samples, dtype=np.float64)
    x = np.asarray(training, dtype=np.float64)
    if training_sq is None:
        training_sq = np.einsum("ij,ij->i", x, x)
    d2 = np.einsum("ij,ij->i", y, y)[:, None] - 2.0 * (y @ x.T) + training_sq[None, :]
    index = np.argmin(d2, axis=1)
    diff = y - x[index]
    return np.sqrt(np.einsum("ij,ij->i", diff, diff)), index


@dataclass(frozen=True)
class CellPopulations:
    """Voronoi cell populations of N training images for M model samples (a Table 1 row).

    Attributes
    ----------
    counts : ndarray of int, shape (n_images,)
        Samples whose nearest training image (L2, image space) is image i; sums to M.
    specificity : float
        Full-appearance-model specificity: mean over samples of the L2 distance to the
        nearest training image (intensity units; the paper's lambda = 1). Lower is better.
    stderr : float
        ``STD / sqrt(M - 1)`` over the M per-sample distances (paper, Section III-A).
    """

    counts: np.ndarray
    specificity: float
    stderr: float

    @property
    def n_samples(self) -> int:
        return int(self.counts.sum())

    @property
    def near_empty_threshold(self) -> float:
        """A cell holding fewer than ``NEAR_EMPTY_FRACTION * M / N`` samples is near-empty."""
        return NEAR_EMPTY_FRACTION * self.n_samples / self.counts.size

    @property
    def empty_fraction(self) -> float:
        """Fraction of training images whose cell no sample reached."""
        return float(np.mean(self.counts == 0))

    @property
    def near_empty_fraction(self) -> float:
        """Fraction of training images with near-empty cells (empty ones included)."""
        return float(np.mean(self.counts < self.near_empty_threshold))

    def to_dict(self) -> dict:
        return {
            "counts": [int(c) for c in self.counts],
            "specificity": self.specificity,
            "stderr": self.stderr,
            "empty_fraction": self.empty_fraction,
            "near_empty_threshold": self.near_empty_threshold,
            "near_empty_fraction": self.near_empty_fraction,
        }


@dataclass(frozen=True)
class AppearanceDiagnostics:
    """The paper's Table 1 for one registration.

    Attributes
    ----------
    registration : str
    n_samples, n_images, seed : int
    n_shape_modes, n_texture_modes, n_modes : int
        Modes of the shape, texture and combined models (all kept).
    shape_weight : float
        ``W`` (intensity units per mm), see :class:`AppearanceModel`.
    raw : CellPopulations
        Cells of the raw affinely aligned training images ``R_i``.
    projected : CellPopulations
        Cells of the projected training images ``synthesise(c_i)``.
    representation_error : ndarray of shape (n_images,)
        ``|R_i - synthesise(c_i)|_2`` (intensity units, over the reference grid).
    training_spacing : ndarray of shape (n_images,)
        ``min_{j != i} |R_i - R_j|_2``: scale against which to judge the representation error.
    reassigned_fraction : float
        Fraction of the samples whose nearest raw image is not the raw version of their
        nearest projected image (0 when projection changes nothing).
    """

    registration: str
    n_samples: int
    n_images: int
    seed: int
    n_shape_modes: int
    n_texture_modes: int
    n_modes: int
    shape_weight: float
    raw: CellPopulations
    projected: CellPopulations
    representation_error: np.ndarray = field(repr=False)
    training_spacing: np.ndarray = field(repr=False)
    reassigned_fraction: float = 0.0

    def to_dict(self) -> dict:
        d = {
            k: getattr(self, k)
            for k in (
                "registration",
                "n_samples",
                "n_images",
                "seed",
                "n_shape_modes",
                "n_texture_modes",
                "n_modes",
                "shape_weight",
                "reassigned_fraction",
            )
        }
        d["near_empty_fraction_of_uniform"] = NEAR_EMPTY_FRACTION
        d["raw"] = self.raw.to_dict()
        d["projected"] = self.projected.to_dict()
        d["representation_error"] = [float(v) for v in self.representation_error]
        d["training_spacing"] = [float(v) for v in self.training_spacing]
        return d


def _populations(counts: np.ndarray, values: np.ndarray) -> CellPopulations:
    m = values.size
    return CellPopulations(
        counts=counts,
        specificity=float(values.mean()),
        stderr=float(values.std() / math.sqrt(m - 1)),
    )


def _check_options(n_samples, seed) -> None:
    if isinstance(n_samples, bool) or not isinstance(n_samples, (int, np.integer)):
        raise ValueError(f"n_samples must be an integer >= 2, got {readable(n_samples)}")
    if not 2 <= n_samples < _search.sampling.MAX_SAMPLES:
        raise ValueError(f"n_samples must be an integer in [2, 2**36), got {readable(n_samples)}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed < 2**63:
        raise ValueError(f"seed must be an integer in [0, 2**63), got {readable(seed)}")


def appearance_diagnostics(
    manifest_or_dict,
    *,
    registration: str,
    n_samples: int = 1000,
    seed: int = 0,
    progress: bool = True,
) -> AppearanceDiagnostics:
    """Voronoi cell populations of the full appearance model's samples (paper, Table 1).

    Parameters
    ----------
    manifest_or_dict : path, dict or Manifest
        The images and their registrations (see :func:`itk_nrreval.load_manifest`).
    registration : str
        The registration whose appearance model is diagnosed.
    n_samples : int
        M, the number of model samples (the paper uses 1,000). Each needs one field
        inversion and one resampling on the reference grid.
    seed : int
        Seed of the counter-based standard normals: the same seed gives the same samples
        and the same table.
    progress : bool
        Progress bars on stderr.

    Returns
    -------
    AppearanceDiagnostics

    Raises
    ------
    InputError
        A manifest problem, an unknown registration, or an appearance model with no variation.
    ValueError
        `n_samples` or `seed` out of range.

    Notes
    -----
    The model and its synthesis are described in the module docstring (affine part, shape
    ``A_i^-1 o T_i``, shape weighting ``W = sqrt(sum var_g / sum var_s)``, all modes kept).
    Samples ``c ~ N(0, diag(combined_variances))`` are synthesised in chunks of at most
    64 images (and at most 2^22 voxel values) and compared with both training sets at once,
    so memory is O((N + chunk) n), never O(M n). Distances are L2 over every voxel of the
    reference grid (the manifest's mask, which lives on the common frame, is not used).
    A cell is *near-empty* below ``NEAR_EMPTY_FRACTION * M / N`` = 10% of the uniform
    share. Twining et al., IEEE TMI, Section III-B and Table 1.
    """
    _check_options(n_samples, seed)
    model, raw = fit_appearance(manifest_or_dict, registration=registration, progress=progress)
    n = model.n_images
    raw_flat = raw.reshape(n, -1)
    projected = np.stack([model.synthesise(c) for c in model.training_params]).reshape(n, -1)
    raw_sq = np.einsum("ij,ij->i", raw_flat, raw_flat)
    proj_sq = np.einsum("ij,ij->i", projected, projected)

    chunk = int(max(1, min(_MAX_CHUNK, _CHUNK_VALUES // raw_flat.shape[1])))
    values = {"raw": np.empty(n_samples), "projected": np.empty(n_samples)}
    counts = {"raw": np.zeros(n, np.int64), "projected": np.zeros(n, np.int64)}
    nearest = {}
    reassigned = 0
    starts = range(0, int(n_samples), chunk)
    for start in progress_bar(
        starts, desc=f"{registration}: samples", total=len(starts), enabled=progress
    ):
        stop = min(int(n_samples), start + chunk)
        images = np.stack([model.synthesise(c) for c in model.sample_params(seed, start, stop)])
        images = images.reshape(stop - start, -1)
        for key, train, sq in (("raw", raw_flat, raw_sq), ("projected", projected, proj_sq)):
            dist, index = nearest_images(images, train, training_sq=sq)
            values[key][start:stop] = dist
            counts[key] += np.bincount(index, minlength=n)
            nearest[key] = index
        reassigned += int(np.count_nonzero(nearest["raw"] != nearest["projected"]))

    gram = raw_flat @ raw_flat.T
    d2 = np.maximum(raw_sq[:, None] - 2.0 * gram + raw_sq[None, :], 0.0)
    np.fill_diagonal(d2, np.inf)
    return AppearanceDiagnostics(
        registration=registration,
        n_samples=int(n_samples),
        n_images=n,
        seed=int(seed),
        n_shape_modes=model.n_shape_modes,
        n_texture_modes=model.n_texture_modes,
        n_modes=model.n_modes,
        shape_weight=model.shape_weight,
        raw=_populations(counts["raw"], values["raw"]),
        projected=_populations(counts["projected"], values["projected"]),
        representation_error=np.linalg.norm(raw_flat - projected, axis=1),
        training_spacing=np.sqrt(d2.min(axis=1)),
        reassigned_fraction=reassigned / n_samples,
    )
