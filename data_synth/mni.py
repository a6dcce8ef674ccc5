"""The MNI152 2009a template that ships inside nilearn, as an image with tissue labels.

nilearn's wheel carries the ICBM 2009a nonlinear symmetric T1 template (skull-stripped) with
grey- and white-matter probability maps, 197 x 233 x 189 voxels of 1 mm. They are read as
files (nilearn itself is never imported, so its heavy dependencies are not needed), smoothed
to the target voxel size and resampled onto an identity-direction LPS grid centred on the
brain. Labels are the voxel-wise argmax of the resampled memberships
(background, grey matter, white matter, CSF/other inside the brain mask).

The ``"t1"`` contrast is the template itself; ``"t2"`` is T2-like, painted from the same
resampled memberships with one intensity per tissue class (CSF bright, grey matter
intermediate, white matter dark: :data:`T2_INTENSITIES`), so both contrasts show the same
anatomy with the same partial volumes.
"""

from __future__ import annotations

import importlib.util
import math
from collections.abc import Mapping
from functools import lru_cache
from pathlib import Path
from types import MappingProxyType

import numpy as np
import SimpleITK as sitk

from .phantom import Phantom, check_contrast

__all__ = ["MNI_LABELS", "T2_INTENSITIES", "make_mni", "mni_data_dir"]

#: Tissue labels of the MNI kind (value -> name).
MNI_LABELS: Mapping[int, str] = MappingProxyType(
    {1: "grey_matter", 2: "white_matter", 3: "csf_other"}
)

#: T2-like intensity of each tissue class of the ``"t2"`` contrast (background 0).
T2_INTENSITIES: Mapping[str, float] = MappingProxyType(
    {"grey_matter": 0.55, "white_matter": 0.32, "csf_other": 1.0}
)

# Physical centre (mm, LPS) of the grids: the middle of the brain's bounding box.
_CENTER_LPS = (0.0, 17.0, 10.0)
_FOV_MM = (180.0, 216.0, 180.0)
_DEFAULT_SPACING = {2: 1.4, 3: 2.0}
_DEFAULT_SIZE_2D = 141


def mni_data_dir() -> Path:
    """The directory of nilearn's installed MNI152 files, without importing nilearn.

    Raises
    ------
    FileNotFoundError
        nilearn is not installed or its data files are missing (install it with
        ``pip install --no-deps nilearn``, as the Makefile does).
    """
    spec = importlib.util.find_spec("nilearn")
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError(
            "the MNI template needs nilearn's data files: pip install --no-deps nilearn"
        )
    path = Path(list(spec.submodule_search_locations)[0]) / "datasets" / "data"
    if not (path / "mni_icbm152_t1_tal_nlin_sym_09a_converted.nii.gz").is_file():
        raise FileNotFoundError(f"{path}: nilearn's MNI152 2009a files are missing")
    return path


@lru_cache(maxsize=1)
def _read_mni() -> tuple[sitk.Image, sitk.Image, sitk.Image]:
    d = mni_data_dir()
    out = []
    for k in ("t1", "gm", "wm"):
        img = sitk.ReadImage(str(d / f"mni_icbm152_{k}_tal_nlin_sym_09a_converted.nii.gz"))
        out.append(img)
    return tuple(out)


def make_mni(
    *,
    dim: int = 2,
    spacing: float | None = None,
    size: int | tuple[int, ...] | None = None,
    z_mm: float = 8.0,
    contrast: str = "t1",
) -> Phantom:
    """The MNI152 2009a T1 template (or a T2-like image of it) and its tissue labels on a grid.

    Parameters
    ----------
    dim : {2, 3}
        2: the axial plane at MNI height `z_mm` (mm; 8 mm passes through the lateral
        ventricles, thalami and basal ganglia); 3: the whole brain.
    spacing : float, optional
        Isotropic voxel size in mm (default 1.4 in 2D, 2.0 in 3D).
    size : int or tuple of int, optional
        Voxels along (x, y[, z]) (ITK order). Default 141 x 141 in 2D (the paper's slice size,
        here covering the whole brain); in 3D enough to cover 180 x 216 x 180 mm.
    z_mm : float
        Height of the 2D slice (MNI z, the same in LPS); ignored in 3D.
    contrast : {"t1", "t2"}
        ``"t1"``: the template's intensities; ``"t2"``: the tissue memberships weighted by
        :data:`T2_INTENSITIES`. The labels do not depend on it.

    Returns
    -------
    Phantom
        ``image`` (float32, T1 scaled to [0, 1], or T2-like in [0, 1]), ``labels`` (uint8,
        :data:`MNI_LABELS`) and
        ``label_names``. The grid has identity direction (LPS) and is centred on the brain.
    """
    if dim not in (2, 3) or isinstance(dim, bool):
        raise ValueError(f"dim must be 2 or 3, got {dim!r}")
    contrast = check_contrast(contrast)
    spacing = _DEFAULT_SPACING[dim] if spacing is None else float(spacing)
    if not (math.isfinite(spacing) and spacing > 0):
        raise ValueError(f"spacing must be a positive number of mm, got {spacing!r}")
    if size is None:
        size = (
            (_DEFAULT_SIZE_2D,) * 2 if dim == 2 else tuple(math.ceil(f / spacing) for f in _FOV_MM)
        )
    elif isinstance(size, (int, np.integer)):
        size = (int(size),) * dim
    size = tuple(int(s) for s in size)
    if len(size) != dim or min(size) < 4:
        raise ValueError(f"size must be {dim} integers >= 4 (x, y[, z] order), got {size!r}")

    t1, gm, wm = _read_mni()
    mask = t1 > 0
    if dim == 2:  # only a slab around the plane matters: crop before smoothing
        k = int(round(t1.TransformPhysicalPointToContinuousIndex((0.0, 0.0, float(z_mm)))[2]))
        lo, hi = max(k - 2 - int(2 * spacing), 0), min(k + 3 + int(2 * spacing), t1.GetSize()[2])
        if hi <= lo:
            raise ValueError(f"z_mm={z_mm} lies outside the MNI template (about -72 to 116 mm)")
        t1, gm, wm, mask = (im[:, :, lo:hi] for im in (t1, gm, wm, mask))
    shrink = max(int(spacing), 1) if dim == 3 else 1
    sigma = 0.5 * math.sqrt(max(spacing**2 - shrink**2, 0.0))  # from `shrink` mm to spacing
    center = _CENTER_LPS if dim == 3 else (_CENTER_LPS[0], _CENTER_LPS[1], float(z_mm))
    ref3 = sitk.Image([*size, 1] if dim == 2 else list(size), sitk.sitkFloat32)
    ref3.SetSpacing([spacing] * 3)
    ref3.SetOrigin(
        [c - (s - 1) * spacing / 2 for c, s in zip(center[:dim], size, strict=True)]
        + ([float(z_mm)] if dim == 2 else [])
    )
    arrays = []
    for img in (t1, gm, wm, mask):
        img = sitk.Cast(img, sitk.sitkFloat32) / (1.0 if img is mask else 255.0)
        if shrink > 1:
            img = sitk.BinShrink(img, [shrink] * 3)
        if sigma > 0:
            img = sitk.SmoothingRecursiveGaussian(img, sigma)
        res = sitk.Resample(img, ref3, sitk.Transform(), sitk.sitkLinear, 0.0)
        arrays.append(sitk.GetArrayFromImage(res)[0] if dim == 2 else sitk.GetArrayFromImage(res))
    t1a, gma, wma, maska = arrays
    csf = np.clip(maska - gma - wma, 0.0, None)
    memberships = np.stack([1.0 - maska, gma, wma, csf])
    labels = np.argmax(memberships, axis=0).astype(np.uint8)
    grid_origin = ref3.GetOrigin()[:dim]
    if contrast == "t1":
        values = t1a
    else:
        t2 = T2_INTENSITIES
        values = t2["grey_matter"] * gma + t2["white_matter"] * wma + t2["csf_other"] * csf
    image = sitk.GetImageFromArray(np.clip(values, 0, None).astype(np.float32))
    lab = sitk.GetImageFromArray(labels)
    for im in (image, lab):
        im.SetSpacing([spacing] * dim)
        im.SetOrigin(grid_origin)
    return Phantom(image, lab, MNI_LABELS)
