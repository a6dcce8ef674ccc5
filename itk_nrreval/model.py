"""The shape-free texture model: PCA of a set of registered images (paper, Section III-B).

The images of a group, registered into one frame, are points in R^n (n voxels). PCA through
the N x N Gram matrix of the centred images gives every non-zero mode (N - 1 for generic
data) at O(N^2 n) cost, computed in voxel chunks so that memory stays O(N^2 + chunk) beyond
the images themselves. Each training image is represented by its *non-normalized* parameter
vector ``b_i`` (coordinates along the unit modes), so Euclidean distances between training
images are preserved exactly; the specificity is then computed in R^(N-1), not R^n.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._errors import InputError
from ._images import Geometry, image_stack, mask_array

__all__ = ["TextureModel"]

_CHUNK_VOXELS = 1 << 16


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
            Fewer than 3 images, images on different grids, NaN or infinite voxels, or
            images that are all identical (no mode of variation).
        """
        stack = image_stack(images)
        n = stack.data.shape[0]
        if n < 3:
            raise InputError(f"need at least 3 images to build a texture model, got {n}")
        flat = stack.data.reshape(n, -1)
        spatial = stack.data.shape[1:]
        mask_arr = mask_array(mask, shape=spatial, geometry=stack.geometry)
        voxels = np.flatnonzero(mask_arr) if mask_arr is not None else None
        n_voxels = flat.shape[1] if voxels is None else voxels.size
        gram = np.zeros((n, n))
        mean = np.empty(n_voxels)
        for start in range(0, n_voxels, _CHUNK_VOXELS):
            stop = min(start + _CHUNK_VOXELS, n_voxels)
            chunk = flat[:, start:stop] if voxels is None else flat[:, voxels[start:stop]]
            chunk_mean = chunk.mean(axis=0)
            centred = chunk - chunk_mean
            mean[start:stop] = chunk_mean
            gram += centred @ centred.T
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
        (:mod:`itk_nrreval.pipeline` sums the Gram matrix over voxel blocks).

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
        eigenvalues, eigenvectors = np.linalg.eigh(gram)
        order = np.argsort(eigenvalues)[::-1]
        eigenvalues, eigenvectors = eigenvalues[order], eigenvectors[:, order]
        # Centred data has rank <= N - 1; eigenvalues below round-off of the largest are zero.
        tol = max(eigenvalues[0], 0.0) * n * 1e-12
        keep = eigenvalues > tol
        if not keep.any():
            raise InputError("all images are identical: the texture model has no mode of variation")
        eigenvalues, eigenvectors = eigenvalues[keep], eigenvectors[:, keep]
        # Fix each eigenvector's sign (largest |component| positive) so results are reproducible
        # across LAPACK builds.
        signs = np.sign(
            eigenvectors[np.argmax(np.abs(eigenvectors), axis=0), np.arange(keep.sum())]
        )
        eigenvectors = eigenvectors * signs
        params = eigenvectors * np.sqrt(eigenvalues)
        return cls(
            training_params=params,
            mode_variances=eigenvalues / (n - 1),
            mean=None if mean is None else np.asarray(mean),
            mask=mask,
            geometry=geometry,
        )
