"""An analytic brain-like phantom in 2D and 3D, with an integer label map.

The head is built from smooth implicit shapes (ellipsoids, some bent or with a folded
surface) in physical millimetres, LPS: +x towards the patient's Left, +y Posterior,
+z Superior, the brain centred near the origin. Shapes are painted in a fixed order, later
ones over earlier ones. Each shape's approximate signed distance ``d`` (mm, negative inside)
gives a partial-volume membership ``clip(0.5 - d / h, 0, 1)`` for a voxel of size ``h``, so the
intensity image has one-voxel soft edges while the label map takes each voxel's majority shape.

The 2D phantom is the axial plane ``z = z_mm`` (default 5 mm, through the lateral
ventricles, thalami and basal ganglia) of the same 3D phantom, the analogue of the paper's
mid-brain slices (Twining et al., Section IV-A).

Two contrasts paint the same shapes (hence the same anatomy, edges and labels) with
different intensities per tissue: ``"t1"`` (white matter bright, CSF dark) and ``"t2"``
(CSF bright, white matter dark, the iron-rich pallidum darker than the other deep nuclei,
fat in the scalp intermediate), for two-modality populations with known correspondence.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np
import SimpleITK as sitk

__all__ = ["CONTRASTS", "PHANTOM_LABELS", "Phantom", "make_phantom", "phantom_grid"]

#: Every label the 3D phantom uses (value -> name). Left is the patient's left (+x, LPS).
PHANTOM_LABELS: Mapping[int, str] = MappingProxyType(
    {
        1: "left_cerebral_white_matter",
        2: "right_cerebral_white_matter",
        3: "left_cerebral_cortex",
        4: "right_cerebral_cortex",
        5: "left_lateral_ventricle",
        6: "right_lateral_ventricle",
        7: "left_thalamus",
        8: "right_thalamus",
        9: "left_caudate",
        10: "right_caudate",
        11: "left_putamen",
        12: "right_putamen",
        13: "left_pallidum",
        14: "right_pallidum",
        15: "third_ventricle",
        16: "cerebrospinal_fluid",
        17: "left_hippocampus",
        18: "right_hippocampus",
        19: "left_amygdala",
        20: "right_amygdala",
        21: "left_cerebellum_white_matter",
        22: "right_cerebellum_white_matter",
        23: "left_cerebellum_cortex",
        24: "right_cerebellum_cortex",
        25: "brain_stem",
        26: "fourth_ventricle",
    }
)

#: The contrasts the generators can paint.
CONTRASTS = ("t1", "t2")

# Intensities in [0, 1] per tissue, for each contrast (T1 first: the original phantom).
_INTENSITIES: Mapping[str, Mapping[str, float]] = MappingProxyType(
    {
        "t1": MappingProxyType(
            {
                "scalp": 0.85,
                "skull": 0.12,
                "csf": 0.15,
                "grey_matter": 0.50,
                "white_matter": 0.80,
                "cerebellum_white_matter": 0.78,
                "brain_stem": 0.72,
                "hippocampus": 0.50,
                "amygdala": 0.52,
                "putamen": 0.58,
                "pallidum": 0.68,
                "caudate": 0.55,
                "thalamus": 0.62,
                "lateral_ventricle": 0.12,
            }
        ),
        "t2": MappingProxyType(
            {
                "scalp": 0.60,
                "skull": 0.06,
                "csf": 1.00,
                "grey_matter": 0.55,
                "white_matter": 0.32,
                "cerebellum_white_matter": 0.34,
                "brain_stem": 0.40,
                "hippocampus": 0.60,
                "amygdala": 0.58,
                "putamen": 0.45,
                "pallidum": 0.28,
                "caudate": 0.52,
                "thalamus": 0.44,
                "lateral_ventricle": 1.00,
            }
        ),
    }
)


def check_contrast(contrast) -> str:
    """`contrast` if it is one of :data:`CONTRASTS`, else ValueError naming the choices."""
    if contrast not in CONTRASTS:
        raise ValueError(f"contrast must be one of {CONTRASTS}, got {contrast!r}")
    return str(contrast)


# Field of view (mm, x y z) of the default grids: the head plus room for a pose change.
_FOV_MM = (200.0, 236.0, 190.0)
_DEFAULT_SPACING = {2: 1.6, 3: 2.0}
_DEFAULT_SIZE_2D = 141

# Cerebrum: ellipsoid centre and semi-axes (mm); its folded white-matter surface.
_CEREBRUM = ((0.0, 0.0, 4.0), (68.0, 86.0, 62.0))
# Wave vectors (cycles per mm would be |k| / 2 pi) of the folding pattern: gyri about 25 mm apart.
_FOLD_K = (
    np.array([[0.21, 0.12, 0.05], [-0.08, 0.22, 0.11], [0.10, -0.06, 0.23], [0.17, 0.15, -0.13]])
    * 1.4
)


@dataclass(frozen=True)
class Phantom:
    """A phantom image and its labels on one grid.

    Attributes
    ----------
    image : sitk.Image
        ``sitkFloat32`` intensities of one contrast (T1-like unless asked otherwise) in
        [0, 1], with partial-volume edges.
    labels : sitk.Image
        ``sitkUInt8`` label map on the same grid, values from `label_names` (0 = background,
        scalp and skull).
    label_names : Mapping[int, str]
        The labels present in `labels` (value -> name), a subset of :data:`PHANTOM_LABELS`
        (the 2D slice misses the structures below the basal ganglia).
    """

    image: sitk.Image
    labels: sitk.Image
    label_names: Mapping[int, str]


def phantom_grid(
    *, dim: int = 2, spacing: float | None = None, size: int | tuple[int, ...] | None = None
) -> sitk.Image:
    """An empty ``sitkFloat32`` image defining a phantom grid centred on the physical origin.

    Parameters
    ----------
    dim : {2, 3}
        Image dimension.
    spacing : float, optional
        Isotropic voxel size in mm (default 1.6 in 2D, 2.0 in 3D).
    size : int or tuple of int, optional
        Voxels along (x, y[, z]) (ITK order). Default: 141 x 141 in 2D; in 3D, enough voxels to
        cover a 200 x 236 x 190 mm field of view.

    Returns
    -------
    sitk.Image
        Zero image with identity direction and the grid centre at (0, 0[, 0]) mm.
    """
    dim = _check_dim(dim)
    spacing = _DEFAULT_SPACING[dim] if spacing is None else float(spacing)
    if not (math.isfinite(spacing) and spacing > 0):
        raise ValueError(f"spacing must be a positive number of mm, got {spacing!r}")
    if size is None:
        if dim == 2:
            size = (_DEFAULT_SIZE_2D,) * 2
        else:
            size = tuple(int(math.ceil(f / spacing)) for f in _FOV_MM)
    elif isinstance(size, (int, np.integer)):
        size = (int(size),) * dim
    size = tuple(int(s) for s in size)
    if len(size) != dim or min(size) < 4:
        raise ValueError(f"size must be {dim} integers >= 4 (x, y[, z] order), got {size!r}")
    grid = sitk.Image(list(size), sitk.sitkFloat32)
    grid.SetSpacing([spacing] * dim)
    grid.SetOrigin([-(s - 1) * spacing / 2 for s in size])
    return grid


def make_phantom(
    *,
    dim: int = 2,
    spacing: float | None = None,
    size: int | tuple[int, ...] | None = None,
    z_mm: float = 5.0,
    contrast: str = "t1",
) -> Phantom:
    """Render the brain-like phantom on a grid.

    Parameters
    ----------
    dim : {2, 3}
        2 for the axial slice at ``z = z_mm``, 3 for the whole head.
    spacing, size
        Grid, as in :func:`phantom_grid`.
    z_mm : float
        Height (mm, LPS +z superior) of the 2D slice; ignored in 3D.
    contrast : {"t1", "t2"}
        The tissue intensities (module docstring); the labels do not depend on it.

    Returns
    -------
    Phantom
        Image, label map and the names of the labels present.

    Notes
    -----
    Painted in this order (later wins): scalp, skull, extracerebral CSF, cerebral cortex,
    cerebral white matter (with gyral fingers), sulcal and interhemispheric CSF, cerebellum
    cortex and white matter, brain stem, fourth ventricle, hippocampus, amygdala, putamen,
    pallidum, caudate, thalamus, lateral ventricles, third ventricle. In 3D at 2 mm the label
    volumes span from about 0.1% (third and fourth ventricles) to over 40% (cortex) of the
    labelled volume; in the 2D slice from about 0.1% to 40%.
    """
    contrast = check_contrast(contrast)
    grid = phantom_grid(dim=dim, spacing=spacing, size=size)
    points = _grid_points(grid, z_mm=z_mm)
    image, labels = render_phantom(points, spacing=grid.GetSpacing(), contrast=contrast)
    img = sitk.GetImageFromArray(image.astype(np.float32))
    img.CopyInformation(grid)
    lab = sitk.GetImageFromArray(labels.astype(np.uint8))
    lab.CopyInformation(grid)
    present = {int(v) for v in np.unique(labels)} - {0}
    names = MappingProxyType({k: v for k, v in PHANTOM_LABELS.items() if k in present})
    return Phantom(img, lab, names)


def _check_dim(dim) -> int:
    if dim not in (2, 3) or isinstance(dim, bool):
        raise ValueError(f"dim must be 2 or 3, got {dim!r}")
    return int(dim)


def _grid_points(grid: sitk.Image, *, z_mm: float) -> np.ndarray:
    """Physical coordinates of the voxel centres, shape ``(3, *numpy_shape)``, rows x, y, z (mm).

    For a 2D grid the z row is the constant `z_mm`. Assumes an identity direction.
    """
    dim = grid.GetDimension()
    axes = [
        grid.GetOrigin()[i] + grid.GetSpacing()[i] * np.arange(grid.GetSize()[i])
        for i in range(dim)
    ]
    # numpy order is reversed: (z, y, x) -- meshgrid with indexing="ij" on reversed axes.
    mesh = np.meshgrid(*reversed(axes), indexing="ij")
    xyz = list(reversed(mesh))
    if dim == 2:
        xyz.append(np.full_like(xyz[0], float(z_mm)))
    return np.stack(xyz)


def _ellipsoid(p: np.ndarray, center, semi, *, bend: float = 0.0) -> np.ndarray:
    """``rho - 1`` of an axis-aligned ellipsoid (negative inside); `bend` curves it in x with y.

    The bent ellipsoid has its centre line at ``x = cx + bend * (y - cy)**2`` (mm), the shape
    of a lateral ventricle seen from above.
    """
    x = p[0] - center[0] - bend * (p[1] - center[1]) ** 2
    y = p[1] - center[1]
    z = p[2] - center[2]
    return np.sqrt((x / semi[0]) ** 2 + (y / semi[1]) ** 2 + (z / semi[2]) ** 2) - 1.0


def _folds(p: np.ndarray) -> np.ndarray:
    """The gyral pattern in [-1, 1]: a fixed sum of plane waves in physical space."""
    flat = p.reshape(3, -1)
    g = np.zeros(flat.shape[1])
    for k, phase in zip(_FOLD_K, (0.3, 1.7, 2.9, 4.1), strict=True):
        g += np.cos(k @ flat + phase)
    return (g / len(_FOLD_K)).reshape(p.shape[1:]) * 1.6


def _signed_distance(f: np.ndarray, spacing_np: tuple[float, ...]) -> np.ndarray:
    """First-order signed distance ``f / |grad f|`` (mm) of the zero level set of `f`."""
    grads = np.gradient(f, *spacing_np)
    norm = np.sqrt(sum(g * g for g in grads))
    return f / np.maximum(norm, 1e-6)


def render_phantom(
    points: np.ndarray, *, spacing, contrast: str = "t1"
) -> tuple[np.ndarray, np.ndarray]:
    """Paint the phantom at grid points.

    Parameters
    ----------
    points : ndarray of shape (3, *numpy_shape)
        Physical (x, y, z) coordinates in mm (LPS) of a regular grid's voxel centres, numpy
        axis order ``(z, y, x)`` (or ``(y, x)`` for a plane).
    spacing : sequence of float
        Voxel size in mm, ITK order (x, y[, z]).
    contrast : {"t1", "t2"}
        The tissue intensities.

    Returns
    -------
    image : ndarray of float64, shape numpy_shape
    labels : ndarray of uint8, shape numpy_shape
    """
    v = _INTENSITIES[check_contrast(contrast)]
    spacing_np = tuple(float(s) for s in reversed(tuple(spacing)))
    h = float(np.mean(spacing_np))
    shape = points.shape[1:]
    image = np.zeros(shape)
    labels = np.zeros(shape, dtype=np.uint8)
    left = points[0] > 0

    def member(f: np.ndarray) -> np.ndarray:
        return np.clip(0.5 - _signed_distance(f, spacing_np) / h, 0.0, 1.0)

    def paint(m: np.ndarray, value: float, label: int | tuple[int, int]) -> None:
        nonlocal image
        image = image * (1.0 - m) + value * m
        inside = m > 0.5
        if isinstance(label, tuple):  # (left, right)
            labels[inside & left] = label[0]
            labels[inside & ~left] = label[1]
        else:
            labels[inside] = label

    cc, cs = _CEREBRUM
    # Head: scalp and skull follow the cerebrum and cerebellum at fixed offsets.
    head_c = (0.0, 6.0, -2.0)
    head_s = (84.0, 104.0, 82.0)
    paint(member(_ellipsoid(points, head_c, head_s)), v["scalp"], 0)
    paint(member(_ellipsoid(points, head_c, tuple(s - 6 for s in head_s))), v["skull"], 0)
    paint(member(_ellipsoid(points, head_c, tuple(s - 13 for s in head_s))), v["csf"], 16)

    rho = _ellipsoid(points, cc, cs) + 1.0
    folds = _folds(points)
    f_brain = rho - 1.0
    paint(member(f_brain), v["grey_matter"], (3, 4))
    f_wm = rho - (0.80 + 0.08 * folds)
    paint(member(f_wm), v["white_matter"], (1, 2))
    # Sulci: CSF where the fold pattern is low, from the surface down to near the white matter.
    d_sulcus = np.maximum.reduce(
        [
            _signed_distance(folds + 0.55, spacing_np),
            -_signed_distance(rho - (0.80 + 0.08 * folds + 0.05), spacing_np),
            _signed_distance(f_brain, spacing_np),
        ]
    )
    paint(np.clip(0.5 - d_sulcus / h, 0, 1), v["csf"], 16)
    # Interhemispheric fissure, above the corpus callosum and at the frontal / occipital poles.
    fissure = np.maximum(np.abs(points[0]) - 1.5, f_brain * 50)
    fissure = np.maximum(fissure, np.minimum(26.0 - points[2], 40.0 - np.abs(points[1])))
    paint(np.clip(0.5 - fissure / h, 0, 1), v["csf"], 16)

    for sign, (wm, gm) in ((1, (21, 23)), (-1, (22, 24))):
        c = (sign * 24.0, 58.0, -38.0)
        rho_cb = _ellipsoid(points, c, (26.0, 24.0, 17.0)) + 1.0
        paint(member(rho_cb - 1.0), v["grey_matter"], gm)
        paint(member(rho_cb - (0.55 + 0.12 * folds)), v["cerebellum_white_matter"], wm)
    shapes: list[tuple[Callable[[], np.ndarray], float, int | tuple[int, int]]] = [
        (lambda: _ellipsoid(points, (0, 24, -36), (11, 13, 28)), v["brain_stem"], 25),
        (lambda: _ellipsoid(points, (0, 40, -38), (5, 3, 6)), v["csf"], 26),  # 4th ventricle
    ]
    for f, value, label in shapes:
        paint(member(f()), value, label)

    paired = [
        # right-side centre (x < 0; mirrored for the left), semi-axes, bend, intensity, labels
        ((-27, 14, -17), (5, 17, 5), 0.0, v["hippocampus"], (17, 18)),
        ((-23, -6, -21), (6, 6, 6), 0.0, v["amygdala"], (19, 20)),
        ((-25, -2, 3), (5, 16, 11), 0.0, v["putamen"], (11, 12)),
        ((-18, 1, 1), (3.5, 8, 6), 0.0, v["pallidum"], (13, 14)),
        ((-14, -12, 11), (5, 12, 9), 0.0, v["caudate"], (9, 10)),
        ((-10, 16, 5), (8, 12, 8), 0.0, v["thalamus"], (7, 8)),
        ((-9, -2, 12), (4.5, 30, 9), 0.003, v["lateral_ventricle"], (5, 6)),
    ]
    for (cx, cy, cz), semi, bend, value, (lab_l, lab_r) in paired:
        for sign, lab in ((1, lab_l), (-1, lab_r)):
            f = _ellipsoid(points, (-sign * cx, cy, cz), semi, bend=sign * bend)
            paint(member(f), value, lab)
    paint(member(_ellipsoid(points, (0, 14, 2), (1.6, 10, 8))), v["csf"], 15)  # 3rd ventricle
    return image, labels
