"""A "registration" that games image similarity: Rohlfing's class-matching cheat.

For testing evaluators: a good verdict must never rank it above genuine registrations.

Rohlfing, "Image similarity and tissue overlaps as surrogates for image registration
accuracy: widely used but unreliable", IEEE TMI 31(2):153-163, 2012.
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
from scipy.ndimage import distance_transform_edt

from itk_nrreval.io.transforms import chain_transform, field_transform


def class_matching_cheat(
    reference_classes: sitk.Image, aligned_classes: sitk.Image, affine: sitk.Transform
) -> sitk.Transform:
    """Map every reference voxel to the nearest voxel of the same class in the subject.

    Parameters
    ----------
    reference_classes : sitk.Image
        Integer class map (labels, or quantised intensities) of the reference.
    aligned_classes : sitk.Image
        The subject's class map after affine alignment, i.e. resampled through `affine` onto
        the reference grid.
    affine : sitk.Transform
        Reference points -> subject points (mm).

    Returns
    -------
    sitk.Transform
        ``T(p) = A(q(p))``, where q(p) is the voxel centre of `aligned_classes` nearest to p
        (physical distance) with the class of p in the reference (p itself when that class
        is absent): ``sitk.CompositeTransform([A, field])``, the field acting first.

    Notes
    -----
    Resampling the subject through T gives, at every reference voxel, a subject value of the
    right class, so class maps overlap almost perfectly and intensity similarity is high: the
    images look alike. Yet within a class the correspondence is nonsense -- each voxel simply
    grabs the nearest voxel of its class -- and where the classes disagree the map jumps:
    neighbouring voxels land on the same point (det J = 0) or cross over (det J < 0), so the
    deformation tears and folds. Only its plausibility gives it away.
    """
    ref = sitk.GetArrayFromImage(reference_classes)
    aligned = sitk.GetArrayFromImage(aligned_classes)
    dim = ref.ndim
    spacing_np = np.asarray(reference_classes.GetSpacing(), np.float64)[::-1]
    index = np.indices(ref.shape)  # (dim, *shape), numpy axis order
    target = index.copy()
    for c in np.unique(ref):
        if not (aligned == c).any():
            continue
        _, nearest = distance_transform_edt(aligned != c, sampling=spacing_np, return_indices=True)
        where = ref == c
        target[:, where] = nearest[:, where]
    # index offsets (numpy order) -> physical displacement (ITK order): D @ diag(s) @ d_index
    d_index = (target - index)[::-1].astype(np.float64)  # ITK order (x, y[, z])
    matrix = np.asarray(reference_classes.GetDirection(), np.float64).reshape(dim, dim)
    matrix = matrix @ np.diag(reference_classes.GetSpacing())
    disp = np.moveaxis(np.tensordot(matrix, d_index, axes=1), 0, -1)  # (*shape, dim)
    field = sitk.GetImageFromArray(np.ascontiguousarray(disp), isVector=True)
    field.CopyInformation(reference_classes)
    return chain_transform([field_transform(field), affine])
