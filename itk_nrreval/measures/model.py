"""The shape-free texture model: PCA of a set of registered images (paper, Section III-B).

The images of a group, registered into one frame, are points in R^n (n voxels). PCA through
the N x N Gram matrix of the centred images gives every non-zero mode (N - 1 for generic
data) at O(N^2 n) cost, computed in voxel chunks so that memory stays O(N^2 + chunk) beyond
the images themselves. Each training image is represented by its *non-normalized* parameter
vector ``b_i`` (coordinates along the unit modes), so Euclidean distances between training
images are preserved exactly; the specificity is then computed in R^(N-1), not R^n.
"""

from __future__ import annotations

import math
from collections.abc import Hashable
from dataclasses import dataclass

import numpy as np

from .._errors import InputError
from ..io._images import Geometry, image_stack, mask_array

__all__ = ["TextureModel", "MixtureModel", "centred_gram"]

_CHUNK_VOXELS = 1 << 16


def _principal_axes(gram: np.ndarray, *, floor: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Non-zero eigenvalues (decreasing) and unit eigenvectors (columns) of a Gram matrix.

    Eigenvalues below round-off of the largest (``n * 1e-12`` relative), or not above
    `floor`, count as zero and are dropped (none may remain). Each eigenvector is signed so
    that its largest-magnitude component is positive, so that results are reproducible
    across LAPACK builds.
    """
    n = gram.shape[0]
    eigenvalues, eigenvectors = np.linalg.eigh(gram)
    order = np.argsort(eigenvalues)[::-1]
    eigenvalues, eigenvectors = eigenvalues[order], eigenvectors[:, order]
    # Centred data has rank <= N - 1; eigenvalues below round-off of the largest are zero.
    tol = max(max(eigenvalues[0], 0.0) * n * 1e-12, floor)
    keep = eigenvalues > tol
    eigenvalues, eigenvectors = eigenvalues[keep], eigenvectors[:, keep]
    signs = np.sign(eigenvectors[np.argmax(np.abs(eigenvectors), axis=0), np.arange(keep.sum())])
    return eigenvalues, eigenvectors * signs


@dataclass(frozen=True, eq=False)
class TextureModel:
    """A linear Gaussian model of registered images, in its own parameter space.

    Build it with :meth:`from_images`.

    Attributes
    ----------
    training_params : ndarray of shape (n_images, n_modes)
        The non-normalized texture parameters ``b_i`` of the training images: their
        coordinates along the unit-length principal modes, relative to the mean image.
        ``|b_i - b_j|_2`` equals the image-space distance ``|I_i - I_j|_2``.
    mode_variances : ndarray of shape (n_modes,)
        Variance along each mode (unbiased, divided by N - 1), in decreasing order.
    mean : ndarray of shape (n_voxels,) or None
        The mean image over the evaluated voxels (inside the mask), flattened in numpy order;
        None for a model built from a Gram matrix alone (it scores samples in parameter
        space, but cannot rebuild images).
    mask : ndarray of bool, shape (*spatial), or None
        The evaluated voxels; None means all.
    geometry : Geometry or None
        The images' grid, when they came with one.
    """

    training_params: np.ndarray
    mode_variances: np.ndarray
    mean: np.ndarray | None
    mask: np.ndarray | None
    geometry: Geometry | None

    @property
    def n_images(self) -> int:
        return self.training_params.shape[0]

    @property
    def n_modes(self) -> int:
        return self.training_params.shape[1]

    @classmethod
    def from_images(cls, images, *, mask=None) -> TextureModel:
        """Fit the model to N registered images on one grid.

        Parameters
        ----------
        images : ndarray of shape (n_images, *spatial), or sequence of sitk.Image or paths
            The registered images, all on one grid (size, spacing, origin, direction).
        mask : ndarray of bool of shape (*spatial), sitk.Image, path, or None
            Evaluate only voxels where the mask is nonzero.

        Raises
        ------
        InputError
            Fewer than 3 images, images on different grids, NaN or infinite voxels, an
            image given twice (the same voxels where the model is fitted: its subject would
            weigh twice), a constant image (no texture), images not 2D or 3D.

        Warns
        -----
        UserWarning
            An image given as a file or an image object that looks like a label map.
        """
        stack = image_stack(images, warn_if_label_like=True)
        n = stack.data.shape[0]
        if n < 3:
            raise InputError(f"need at least 3 images to build a texture model, got {n}")
        flat = stack.data.reshape(n, -1)
        spatial = stack.data.shape[1:]
        mask_arr = mask_array(mask, shape=spatial, geometry=stack.geometry)
        voxels = np.flatnonzero(mask_arr) if mask_arr is not None else None
        gram, mean, low, high = centred_gram(flat, voxels)
        _check_images_differ(gram, low, high, masked=voxels is not None)
        return cls.from_gram(gram, mean=mean, mask=mask_arr, geometry=stack.geometry)

    @classmethod
    def from_gram(
        cls,
        gram: np.ndarray,
        *,
        mean: np.ndarray | None = None,
        mask: np.ndarray | None = None,
        geometry: Geometry | None = None,
    ) -> TextureModel:
        """The model from the Gram matrix of the centred images, computed elsewhere.

        This is how a model is built when the images never sit in one process
        (:mod:`itk_nrreval._pipeline` sums the Gram matrix over voxel blocks).

        Parameters
        ----------
        gram : ndarray of shape (n_images, n_images)
            ``G_ij = sum_v (I_i(v) - mean(v)) (I_j(v) - mean(v))`` over the evaluated voxels.
        mean : ndarray of shape (n_voxels,), optional
            The mean image over the evaluated voxels (None: unknown; see ``mean``).
        mask : ndarray of bool of shape (*spatial), optional
        geometry : Geometry, optional

        Raises
        ------
        InputError
            Fewer than 3 images, or no mode of variation (all images identical).
        """
        gram = np.asarray(gram, dtype=np.float64)
        n = gram.shape[0]
        if gram.shape != (n, n):
            raise ValueError(f"gram: expected a square matrix, got shape {gram.shape}")
        if n < 3:
            raise InputError(f"need at least 3 images to build a texture model, got {n}")
        eigenvalues, eigenvectors = _principal_axes(gram)
        if eigenvalues.size == 0:
            raise InputError("all images are identical: the texture model has no mode of variation")
        params = eigenvectors * np.sqrt(eigenvalues)
        return cls(
            training_params=params,
            mode_variances=eigenvalues / (n - 1),
            mean=None if mean is None else np.asarray(mean),
            mask=mask,
            geometry=geometry,
        )


@dataclass(frozen=True, eq=False)
class MixtureModel:
    """A Gaussian mixture of texture models: one Gaussian per group of images (issue 19).

    For a group of registered images split between groups (e.g. modalities, the paper's
    closing discussion), each group g of N_g images has its own Gaussian: the group's mean
    and its PCA with every non-zero mode (N_g - 1 for generic data, unbiased variances
    divided by N_g - 1), weighted ``N_g / N`` in the mixture. Everything is expressed in the
    parameter space of the :class:`TextureModel` of all N images (the *joint* PCA space):
    every group's mean and modes lie in the span of the N centred images, so a group sample
    ``mean_g + sum_k z_k sqrt(var_gk) u_gk`` is a point there, its L2 distance to a training
    image equals their image-space distance, and L1 distances are sums along the joint modes,
    as for a single group. Build it with :meth:`from_model`.

    Attributes
    ----------
    joint : TextureModel
        The model of all N images; its ``training_params`` (n_images, n_modes) are the
        training points every sample is compared with.
    groups : tuple of hashable
        The group labels, in order of first appearance in the image order.
    image_groups : ndarray of int, shape (n_images,)
        Each training image's group, an index into `groups`.
    centres : ndarray of shape (n_groups, n_modes)
        Each group's mean image, in joint parameters.
    bases : tuple of ndarray, one per group, of shape (n_group_modes, n_modes)
        Row k is the group's k-th unit mode (in joint parameters) times its standard
        deviation ``sqrt(mode_variances[g][k])``, so a sample of group g is
        ``centres[g] + z @ bases[g]`` for standard normals z. Each mode is signed so that the
        group image with the largest-magnitude coordinate along it has a positive coordinate.
    mode_variances : tuple of ndarray, one per group, of shape (n_group_modes,)
        The group's mode variances (unbiased, divided by N_g - 1), in decreasing order.
    """

    joint: TextureModel
    groups: tuple[Hashable, ...]
    image_groups: np.ndarray
    centres: np.ndarray
    bases: tuple[np.ndarray, ...]
    mode_variances: tuple[np.ndarray, ...]

    @property
    def n_images(self) -> int:
        return self.joint.n_images

    @property
    def n_modes(self) -> int:
        """Modes of the joint parameter space, where distances are taken."""
        return self.joint.n_modes

    @property
    def n_groups(self) -> int:
        return len(self.groups)

    @property
    def group_sizes(self) -> np.ndarray:
        """N_g, shape (n_groups,)."""
        return np.bincount(self.image_groups, minlength=self.n_groups)

    @property
    def weights(self) -> np.ndarray:
        """The mixture weights ``N_g / N``, shape (n_groups,)."""
        return self.group_sizes / self.n_images

    @classmethod
    def from_model(cls, model: TextureModel, groups) -> MixtureModel:
        """The mixture of `model`'s training images split by `groups`.

        `model` may come from images (:meth:`TextureModel.from_images`) or from a Gram matrix
        alone (:meth:`TextureModel.from_gram`): only its training parameters are used, so the
        mixture too is computable from the N x N Gram matrix of the centred images.

        Parameters
        ----------
        model : TextureModel
            The model of all N images.
        groups : sequence of hashable, length n_images
            Each image's group label (e.g. ``"t1"``, ``"t2"``), in image order.

        Raises
        ------
        InputError
            `groups` is not a sequence of N hashable labels, a group has fewer than 2
            images, or a group's images are all identical (no mode of variation).
        """
        names, image_groups = _group_labels(groups, model.n_images)
        params = model.training_params
        # The joint parameters carry round-off of the joint scale: a group's eigenvalue below
        # the joint model's zero threshold is no variation (e.g. a group of identical images).
        floor = float(model.mode_variances[0]) * (model.n_images - 1) * model.n_images * 1e-12
        centres = np.empty((len(names), model.n_modes))
        bases, variances = [], []
        for g, name in enumerate(names):
            members = np.flatnonzero(image_groups == g)
            n_g = members.size
            if n_g < 2:
                raise InputError(
                    f"groups: group {name!r} has only 1 image (image {members[0]}); "
                    "every group needs at least 2 images"
                )
            centres[g] = params[members].mean(axis=0)
            centred = params[members] - centres[g]
            eigenvalues, eigenvectors = _principal_axes(centred @ centred.T, floor=floor)
            if eigenvalues.size == 0:
                raise InputError(
                    f"groups: the {n_g} images of group {name!r} are identical: "
                    "the group has no mode of variation"
                )
            # Unit mode k is centred.T @ e_k / sqrt(lambda_k); times sqrt(lambda_k / (N_g - 1)).
            bases.append(np.ascontiguousarray(eigenvectors.T @ centred) / math.sqrt(n_g - 1))
            variances.append(eigenvalues / (n_g - 1))
        return cls(
            joint=model,
            groups=names,
            image_groups=image_groups,
            centres=centres,
            bases=tuple(bases),
            mode_variances=tuple(variances),
        )


def _group_labels(groups, n_images: int) -> tuple[tuple[Hashable, ...], np.ndarray]:
    """Check per-image group labels: (names in order of first appearance, index per image).

    Raises
    ------
    InputError
        Not a sequence of `n_images` hashable labels (a string is refused: pass a list).
    """
    if isinstance(groups, (str, bytes)):
        raise InputError(
            f"groups: expected one label per image (a list of {n_images}), got a string"
        )
    try:
        labels = list(groups)
    except TypeError:
        raise InputError(
            f"groups: expected one label per image (a list of {n_images}), "
            f"got {type(groups).__name__}"
        ) from None
    if len(labels) != n_images:
        raise InputError(
            f"groups: {len(labels)} labels for {n_images} images (one label per image)"
        )
    index: dict[Hashable, int] = {}
    image_groups = np.empty(n_images, dtype=np.int64)
    for i, label in enumerate(labels):
        if isinstance(label, np.generic):
            label = label.item()
        try:
            image_groups[i] = index.setdefault(label, len(index))
        except TypeError:
            raise InputError(
                f"groups[{i}]: a group label must be hashable, got {type(label).__name__}"
            ) from None
    return tuple(index), image_groups


def centred_gram(flat: np.ndarray, voxels: np.ndarray | None = None):
    """The Gram matrix of the centred rows of `flat`, their mean, and each row's range.

    Parameters
    ----------
    flat : ndarray of shape (N, n_values)
    voxels : ndarray of int, optional
        The columns to use (a mask's flat indices); default all.

    Returns
    -------
    gram : ndarray of shape (N, N)
    mean : ndarray of shape (n_used,)
    low, high : ndarray of shape (N,)
        Each row's least and greatest value over the columns used.

    Streams over chunks of ``_CHUNK_VOXELS`` columns: no centred copy of `flat` is made.
    """
    n = flat.shape[0]
    n_voxels = flat.shape[1] if voxels is None else voxels.size
    gram = np.zeros((n, n))
    mean = np.empty(n_voxels)
    low, high = np.full(n, np.inf), np.full(n, -np.inf)
    for start in range(0, n_voxels, _CHUNK_VOXELS):
        stop = min(start + _CHUNK_VOXELS, n_voxels)
        chunk = flat[:, start:stop] if voxels is None else flat[:, voxels[start:stop]]
        low, high = np.minimum(low, chunk.min(axis=1)), np.maximum(high, chunk.max(axis=1))
        chunk_mean = chunk.mean(axis=0)
        centred = chunk - chunk_mean
        mean[start:stop] = chunk_mean
        gram += centred @ centred.T
    return gram, mean, low, high


def _check_images_differ(gram: np.ndarray, low: np.ndarray, high: np.ndarray, *, masked: bool):
    """Refuse an image given twice and a constant image, as the manifest check does for
    evaluate's images: both would change the scores without a word (a subject counted twice
    draws the model's samples near it twice as often).

    Parameters
    ----------
    gram : ndarray of shape (N, N)
        The centred images' Gram matrix: images i and j are the same where
        ``gram[i, i] + gram[j, j] - 2 gram[i, j]`` (their squared distance) is 0, to
        round-off.
    low, high : ndarray of shape (N,)
        Each image's least and greatest voxel value where the model is fitted.
    masked : bool
        Whether a mask chose those voxels (the message says so).
    """
    where = " inside the mask" if masked else ""
    if np.all(high - low == 0) and np.all(low == low[0]):
        raise InputError("all images are identical: the texture model has no mode of variation")
    diagonal = np.diag(gram)
    squared = diagonal[:, None] + diagonal[None, :] - 2.0 * gram
    tolerance = 1e-12 * max(float(diagonal.max()), np.finfo(float).tiny)
    for j in range(1, gram.shape[0]):
        same = np.flatnonzero(squared[j, :j] <= tolerance)
        if same.size:
            raise InputError(
                f"images[{j}] is the same as images[{same[0]}] (identical voxels{where}): give "
                "each image once (twice, its subject weighs twice in the model)"
            )
    constant = np.flatnonzero(high - low == 0)
    if constant.size:
        raise InputError(
            f"images[{constant[0]}] is constant ({low[constant[0]]:g}{where}): an image with no "
            "texture scores as an outlier of the model"
        )
