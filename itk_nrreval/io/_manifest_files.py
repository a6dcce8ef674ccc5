"""The checks of the files a manifest names, made before any heavy work so that every problem
is reported at once: headers first (each image's and transform's dimension, an image's
components, an evaluation image's or brain mask's place beside its image), then what the
images, label maps and brain masks hold (NaN or constant images, an image listed twice,
negative labels, a label map off its image, a mask that is not binary); and the matching of
image files given elsewhere (a command line's) to a manifest's images.

:func:`check_manifest_files` is what :func:`itk_nrreval.io.manifest.load_manifest` runs; a
manifest's structure is read before, entry by entry (:mod:`itk_nrreval.io._manifest_entries`). A
manifest is passed in as its :class:`~itk_nrreval.io.manifest.Manifest`, not annotated as one:
that module imports this one.
"""

from __future__ import annotations

import math
import os
import re
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from .._errors import InputError
from .._executors import ITK_READ_LOCK
from ._cache import content_digest
from ._elastix_files import (
    elastix_file_dimension,
    is_elastix_parameter_file,
    read_elastix_transform,
)
from ._foreign_transforms import ForeignTransform, plain_field_problem
from ._images import (
    Geometry,
    InMemoryImage,
    LabelSummary,
    dimension_problem,
    label_summary,
    read_header,
    read_image,
    voxel_range,
)
from ._itk_hdf5 import transform_dimension as hdf5_transform_dimension
from ._manifest_entries import relative_path
from .transforms import (
    FIELD_SUFFIXES,
    TRANSFORM_SUFFIXES,
    InMemoryTransform,
    field_components_problem,
    file_suffix,
)

__all__ = [
    "MIN_IMAGES",
    "check_manifest_files",
    "check_image_contents",
    "image_info",
    "order_as_in_manifest",
]


# ----------------------------------------------------------------------------- headers


def image_info(path: Path) -> tuple[int, int]:
    """(dimension, components) of an image from its header."""
    reader = read_header(path)
    return reader.GetDimension(), reader.GetNumberOfComponents()


_TEXT_HEADER = re.compile(r"^Transform:\s*\S+?_(\d)_(\d)\s*$")


def _transform_file_dimension(path: Path) -> int:
    """Spatial dimension of a transform file or displacement-field image, cheaply.

    Text transform files are scanned for their ``Transform: Name_double_D_D`` line (elastix
    parameter files are read with their initial transforms, cheap text); HDF5 files of
    composites, affine maps and displacement fields from their layout
    (:func:`~itk_nrreval.io._itk_hdf5.transform_dimension`); other transform files are read whole;
    displacement-field images give their header's dimension.

    Raises
    ------
    RuntimeError, ValueError
        When the file cannot be read as a transform.
    """
    suffix = file_suffix(path)
    if suffix in FIELD_SUFFIXES:
        dim, comps = image_info(path)
        if comps != dim:
            raise ValueError(field_components_problem(dim, comps))
        return dim
    if suffix == ".txt" and is_elastix_parameter_file(path):
        read_elastix_transform(path)  # the whole chain of runs: every file found and readable
        return elastix_file_dimension(path)
    if suffix in (".txt", ".tfm"):
        with open(path, errors="replace") as fh:
            for line in fh:
                m = _TEXT_HEADER.match(line.strip())
                if m:
                    return int(m.group(1))
        raise ValueError("no 'Transform:' line")
    if suffix in (".h5", ".hdf5") and (dim := hdf5_transform_dimension(path)) is not None:
        return dim
    with ITK_READ_LOCK:
        return sitk.ReadTransform(str(path)).GetDimension()


def _check_item(item, what: str, dim: int | None, problems: list[str]) -> None:
    field = None  # how to name a displacement field given as an image (a file or an object)
    if isinstance(item, ForeignTransform):
        try:
            d = item.check()
        except InputError as exc:
            problems.append(f"{what}: {exc}")
            return
    elif isinstance(item, InMemoryTransform):
        d = item.dimension
        field = f"the in-memory {item.source}" if isinstance(item.value, sitk.Image) else None
    else:
        if item.is_dir():
            problems.append(f"{what}: {item} is a folder, expected a transform file")
            return
        if not item.is_file():
            problems.append(f"{what}: file not found: {item}")
            return
        suffix = file_suffix(item)
        if suffix not in TRANSFORM_SUFFIXES + FIELD_SUFFIXES:
            problems.append(
                f"{what}: {item.name}: unknown transform format (expected one of "
                f"{', '.join(TRANSFORM_SUFFIXES + FIELD_SUFFIXES)})"
            )
            return
        try:
            d = _transform_file_dimension(item)
        except (RuntimeError, ValueError, OSError) as exc:
            reason = next((ln for ln in str(exc).splitlines() if ln.strip()), "unreadable")
            problems.append(f"{what}: cannot read transform {item.name} ({reason.strip()[:120]})")
            return
        field = item.name if suffix in FIELD_SUFFIXES else None
        if field is not None and (problem := plain_field_problem(item)) is not None:
            problems.append(f"{what}: {problem}")
            return
    if dim is not None and d != dim:
        if field is not None:  # an image: named, as images are
            problems.append(f"{what}: {field} is a {d}D displacement field, the images are {dim}D")
        else:
            problems.append(f"{what}: {d}D transform for {dim}D images")


def _image_header(item, what: str, problems: list[str]) -> tuple[int, str, bool] | None:
    """(dimension, name to show, whether scalar) of an image file or object.

    The name is the file's name, or the object's label (``the in-memory sitk.Image``);
    None when the file is missing or unreadable. A problem is added for each of these, and
    for an image of more than one component (not scalar).
    """
    if isinstance(item, InMemoryImage):
        d, comps = item.image.GetDimension(), item.image.GetNumberOfComponentsPerPixel()
        shown = item.label
    else:
        if item.is_dir():
            problems.append(f"{what}: {item} is a folder, expected an image file")
            return None
        if not item.is_file():
            problems.append(f"{what}: file not found: {item}")
            return None
        try:
            d, comps = image_info(item)
        except RuntimeError:
            problems.append(f"{what}: cannot read image {item}")
            return None
        shown = item.name
    if comps != 1:
        problems.append(f"{what}: {shown} has {comps} components, expected a scalar image")
    return d, shown, comps == 1


_SAME_SPACE = 0.5
"""An evaluation image and its image must share at least this fraction of the smaller one's
physical extent (bounding boxes in mm): a scan of the same subject in the same space."""


def _shown(item) -> str:
    return item.label if isinstance(item, InMemoryImage) else Path(item).name


@dataclass(frozen=True)
class _Grid:
    """An image's grid from its header: size, spacing, origin (ITK order) and direction."""

    size: np.ndarray
    spacing: np.ndarray
    origin: np.ndarray
    direction: np.ndarray  # d x d

    @classmethod
    def of(cls, item) -> _Grid | None:
        """The grid of an image file or object; None when it cannot be read (another check
        reports that)."""
        try:
            info = item.image if isinstance(item, InMemoryImage) else read_header(item)
        except RuntimeError:
            return None
        d = len(info.GetSize())
        return cls(
            np.asarray(info.GetSize()),
            np.asarray(info.GetSpacing()),
            np.asarray(info.GetOrigin()),
            np.asarray(info.GetDirection()).reshape(d, d),
        )

    def box(
        self, voxels: tuple[tuple[int, ...], tuple[int, ...]] | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box (mm, LPS) of the grid's voxels, or of those in the index
        box `voxels` (first and last index per axis, ITK order), voxel corners included."""
        first, last = (np.zeros_like(self.size), self.size - 1) if voxels is None else voxels
        d = len(self.size)
        ends = [(f - 0.5, n + 0.5) for f, n in zip(first, last, strict=True)]
        corners = np.array(np.meshgrid(*ends)).reshape(d, -1)
        points = self.origin[:, None] + self.direction @ (self.spacing[:, None] * corners)
        return points.min(axis=1), points.max(axis=1)


def _physical_box(item) -> tuple[np.ndarray, np.ndarray] | None:
    """Axis-aligned bounding box (mm, LPS) of an image's voxels, corners included, from its
    header; None when it cannot be read (another check reports that)."""
    grid = _Grid.of(item)
    return None if grid is None else grid.box()


def _shared_extent(a, b) -> float | None:
    """Volume of the intersection of two images' bounding boxes over the smaller box's."""
    box_a, box_b = _physical_box(a), _physical_box(b)
    if box_a is None or box_b is None or len(box_a[0]) != len(box_b[0]):
        return None
    inter = np.clip(np.minimum(box_a[1], box_b[1]) - np.maximum(box_a[0], box_b[0]), 0, None)
    smaller = min(np.prod(box_a[1] - box_a[0]), np.prod(box_b[1] - box_b[0]))
    return float(np.prod(inter) / smaller) if smaller > 0 else None


def _outside_mm(box, of) -> float:
    """How far (mm) bounding box `box` reaches outside bounding box `of`, along any axis."""
    return float(np.max(np.maximum(np.maximum(of[0] - box[0], box[1] - of[1]), 0.0)))


def _off_image_mm(image, label_map, labels: LabelSummary) -> float | None:
    """How far (mm) a label map's labelled voxels reach outside its image, or None when the
    label map lies on its image.

    Compared as bounding boxes (mm), give or take one voxel of the coarser of the two grids
    along each of its axes: a label map resampled to another resolution over the same field
    of view has its edges that close to the image's (its size rounded to whole voxels, its
    first voxel's centre kept or moved by half a voxel), and on an oblique grid one voxel's
    offset spreads over up to sqrt(d) axes of the bounding box. A label map lies on its
    image when its box lies within the image's (the same field of view, or a crop); when
    its box holds the image's (a larger field of view: the image cropped after labelling, a
    padded or atlas grid) and some of its labelled voxels lie on the image; or when its
    labelled voxels lie within the image's box. Otherwise its box is moved against the
    image's (a wrong origin, or an origin in RAS read as LPS): the labels would be scored
    where they are not.
    """
    img, lab = _Grid.of(image), _Grid.of(label_map)
    if img is None or lab is None or len(img.size) != len(lab.size) or labels.foreground is None:
        return None
    tolerance = math.sqrt(len(img.size)) * max(float(img.spacing.max()), float(lab.spacing.max()))
    on, box = img.box(), lab.box()
    if _outside_mm(box, on) <= tolerance:  # the same field of view, or a crop
        return None
    labelled = lab.box(labels.foreground)
    off = _outside_mm(labelled, on)
    if off <= tolerance:
        return None
    holds_image = _outside_mm(on, box) <= tolerance
    meets_image = bool(np.all(np.minimum(labelled[1], on[1]) > np.maximum(labelled[0], on[0])))
    return None if holds_image and meets_image else off


def _check_image(item, what: str, dim: int | None, problems: list[str]) -> bool:
    """Check an image's header; whether its voxels can be looked at (read, scalar, and of
    the images' dimension)."""
    header = _image_header(item, what, problems)
    if header is not None and dim is not None and header[0] != dim:
        problems.append(f"{what}: {header[1]} is {header[0]}D, the images are {dim}D")
        return False
    return header is not None and dim is not None and header[2]


def _images_dimension(images, problems: list[str]) -> tuple[int | None, set[int]]:
    """The images' dimension, set by the majority; each image that differs is named. With
    it, the images whose voxels can be looked at (read, scalar, of that dimension).

    The dimension is None when no image could be read or the majority's dimension is not
    2 or 3 (one problem then says so; nothing else is compared with it).
    """
    headers = {}
    for i, item in enumerate(images):
        if (header := _image_header(item, f"images[{i}]", problems)) is not None:
            headers[i] = header
    if not headers:
        return None, set()
    counts = Counter(d for d, _, _ in headers.values())
    # ties go to a usable dimension, then to the first image's
    dim = max(counts, key=lambda d: (counts[d], dimension_problem(d) is None))
    if (problem := dimension_problem(dim)) is not None:
        first = next(i for i, (d, _, _) in headers.items() if d == dim)
        which = "all" if counts[dim] == len(headers) else f"{counts[dim]} of"
        problems.append(
            f"images: {which} {len(headers)} images are {dim}D (images[{first}]: "
            f"{headers[first][1]} {problem})"
        )
        return None, set()
    others = len(headers) - 1
    agree = (
        f"the other {others}" if counts[dim] == others else f"{counts[dim]} of the other {others}"
    )
    for i, (d, shown, _) in headers.items():
        if d != dim:
            problems.append(f"images[{i}]: {shown} is {d}D; {agree} images are {dim}D")
    return dim, {i for i, (d, _, scalar) in headers.items() if d == dim and scalar}


MIN_IMAGES = 3
"""The fewest images a manifest may list: a texture model of 2 images has one mode, and
every score compares an image with the others."""


def check_manifest_files(m, problems: list[str]) -> list[str]:
    """The file checks: headers first, then what the images and label maps hold
    (:func:`_check_voxels`). Returns the warnings to give if nothing is refused."""
    if m.n_images < MIN_IMAGES:
        problems.append(
            f"images: {m.n_images} image{'s' if m.n_images != 1 else ''}; a texture model "
            f"needs at least {MIN_IMAGES}"
        )
    dim, images_ok = _images_dimension(m.images, problems)
    labels_ok = {
        i for i, p in enumerate(m.labels or ()) if _check_image(p, f"labels[{i}]", dim, problems)
    }
    scored_ok = set()
    for i, p in enumerate(m.evaluation_images or ()):
        if _check_image(p, f"evaluation_images[{i}]", dim, problems):
            scored_ok.add(i)
        if (shared := _shared_extent(m.images[i], p)) is not None and shared < _SAME_SPACE:
            problems.append(
                f"evaluation_images[{i}]: {_shown(p)} shares {shared:.0%} of its physical "
                f"extent with images[{i}] {_shown(m.images[i])}; it must be the same subject "
                "in the same physical space (another contrast or scan, co-registered)"
            )
    if m.mask is not None:
        _check_image(m.mask, "mask", dim, problems)
    masks_ok = {
        i
        for i, p in enumerate(m.masks or ())
        if _check_image(p, f"masks[{i}]", dim, problems)
        and _mask_on_its_image(p, i, m.images[i], i in images_ok, problems)
    }
    for name, r in m.registrations.items():
        where = f"registrations.{name}"
        _check_image(r.reference, f"{where}.reference", dim, problems)
        for i, chain in enumerate(r.transforms):
            for j, item in enumerate(chain):
                w = f"{where}.transforms[{i}]" + (f"[{j}]" if len(chain) > 1 else "")
                _check_item(item, w, dim, problems)
        if r.frame_transform is not None:
            _check_item(r.frame_transform, f"{where}.frame_transform", dim, problems)
    _check_masks_held(m, masks_ok, problems)
    return _check_voxels(m, images_ok, scored_ok, labels_ok, problems)


_MASK_GRID_TOLERANCE = 1e-4
"""How far a brain mask's spacing, origin (mm) and direction cosines may differ from its
image's: a pipeline writes both from one header, and NIfTI keeps them in float32."""


def _mask_on_its_image(mask, i: int, image, image_ok: bool, problems: list[str]) -> bool:
    """Whether brain mask `i` lies on its image's grid (the same size, spacing, origin and
    direction): it is resampled through the image's transforms, which map into the image's
    space. Against an image that could not be read it is not compared (False; the image's
    own problem is reported)."""
    if not image_ok:
        return False
    mask_grid, image_grid = _geometry(mask), _geometry(image)
    if mask_grid is None or image_grid is None:
        return False
    problem = image_grid.mismatch(mask_grid, tol=_MASK_GRID_TOLERANCE)
    if problem is not None:
        problems.append(
            f"masks[{i}]: {_shown(mask)} is not on the grid of images[{i}] {_shown(image)}: "
            f"{problem}; a brain mask lies on its image's grid"
        )
        return False
    return True


def _geometry(item) -> Geometry | None:
    """The grid of an image file or object from its header; None when unreadable (another
    check reports that)."""
    try:
        info = item.image if isinstance(item, InMemoryImage) else read_header(item)
    except RuntimeError:
        return None
    return Geometry.from_image(info)


def _check_masks_held(m, ok: set[int], problems: list[str]) -> None:
    """Refuse a brain mask that is not binary (values other than 0 and 1: a probability map,
    or a label map given as a mask) or holds no voxel: its Dice would say nothing about the
    registration. Each mask is read once (a brain mask at 1 mm: about 0.1 s)."""
    for i in sorted(ok):
        item, what = m.masks[i], f"masks[{i}]"
        try:
            mask = read_image(item, what="brain mask")
        except InputError as exc:
            problems.append(f"{what}: {_reader_problem(exc, item)}")
            continue
        voxels = sitk.GetArrayViewFromImage(mask)  # a view: `mask` holds its buffer
        other = voxels[(voxels != 0) & (voxels != 1)]
        if other.size:
            found = np.unique(other)
            listed = ", ".join(f"{v:g}" for v in found[:3]) + (", ..." if found.size > 3 else "")
            problems.append(
                f"{what}: {_shown(item)} holds values other than 0 and 1 ({listed}): a brain "
                "mask is binary"
            )
        elif not voxels.any():
            problems.append(f"{what}: {_shown(item)} is empty (every voxel is 0)")


# ----------------------------------------------------------------------------- voxel checks


def _check_voxels(
    m, images_ok: set[int], scored_ok: set[int], labels_ok: set[int], problems: list
) -> list[str]:
    """What the images and label maps hold, for those whose headers passed (the `_ok`
    indices): each is read once, before any heavy work, so that what would change the
    numbers without a word is refused with every other problem.

    Images and evaluation images (:func:`_check_images_held`): NaN or infinite values, a
    damaged NIfTI file, a constant image, an image listed twice. Label maps
    (:func:`_check_labels_held`): values that are not integers or are negative, a label map
    off its image; a label of one subject only is a warning (returned).

    Cost per image: a NIfTI file's slab-by-slab read (:func:`~itk_nrreval.io._images.voxel_range`)
    and ITK's read for its content digest (:func:`~itk_nrreval.io._cache.content_digest`), both
    kept for the process: the run that follows makes both anyway (its reader's checks, its
    cache keys) and finds them done. Per label map: one read, its values sorted once.
    """
    _check_images_held(m.images, "images", images_ok, problems)
    if m.evaluation_images is not None:
        _check_images_held(m.evaluation_images, "evaluation_images", scored_ok, problems)
    if m.labels is None:
        return []
    return _check_labels_held(m, labels_ok, images_ok, problems)


def _reader_problem(exc: InputError, item) -> str:
    """The reader's message about `item`, which names a file by its path, as it does
    everywhere; an object, which it names by its item (``images[2]: ...``), by what the
    manifest's other problems call it (``the in-memory sitk.Image: ...``): the item leads
    the problem already."""
    text = str(exc)
    if isinstance(item, InMemoryImage):
        text = f"{item.label}: {text.removeprefix(f'{item.name}: ')}"
    return text


def _file_identity(item) -> tuple[int, int] | None:
    """(device, inode) of an image file, the same through links and spellings; None for an
    object."""
    if isinstance(item, InMemoryImage):
        return None
    stat = os.stat(item)
    return stat.st_dev, stat.st_ino


def check_image_contents(paths: Sequence[str | os.PathLike], *, key: str = "images") -> None:
    """Refuse what a list of image files holds that would change a score without a word,
    as the manifest check does for its images: an image listed twice (the same file, or the
    same voxels on the same grid), a constant image, NaN or infinite voxels.

    Files that do not exist are left to the reader, which names them.

    Raises
    ------
    InputError
        One line: the first problem, naming the file by ``key[i]`` and its path, and how
        many more there are.
    """
    paths = [str(p) for p in paths]
    problems: list[str] = []
    _check_images_held(paths, key, {i for i, p in enumerate(paths) if os.path.isfile(p)}, problems)
    if problems:
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise InputError(problems[0] + more)


def _check_images_held(items: Sequence, key: str, ok: set[int], problems: list[str]) -> None:
    """Refuse an image with a NaN or an infinity, a constant one (no texture: an all-zero
    image scores as an outlier of the model), and an image listed twice, as the same file or
    as the same voxels on the same grid (a subject counted twice: the model's samples fall
    near it twice as often)."""
    files: dict[tuple[int, int], int] = {}
    contents: dict[str, int] = {}
    for i in sorted(ok):
        item, what = items[i], f"{key}[{i}]"
        if (identity := _file_identity(item)) is not None:
            if identity in files:
                j = files[identity]
                problems.append(
                    f"{what} {_shown(item)} is the same file as {key}[{j}] {_shown(items[j])}: "
                    "list each image once (twice, its subject weighs twice in the model)"
                )
                continue  # its content is that image's, checked there
            files[identity] = i
        try:
            low, high = voxel_range(item, what="image")
        except InputError as exc:
            problems.append(f"{what}: {_reader_problem(exc, item)}")
            continue
        if low == high:
            problems.append(
                f"{what}: {_shown(item)} is constant (every voxel is {low:g}): it holds no "
                "texture to score"
            )
            continue
        digest = item.content_digest if isinstance(item, InMemoryImage) else content_digest(item)
        if digest in contents:
            j = contents[digest]
            problems.append(
                f"{what}: {_shown(item)} holds the same voxels on the same grid as {key}[{j}] "
                f"{_shown(items[j])}: list each image once (twice, its subject weighs twice in "
                "the model)"
            )
        else:
            contents[digest] = i


_LABELS_NAMED = 4  # labels of one subject named in the warning; the rest are counted


def _check_labels_held(m, ok: set[int], images_ok: set[int], problems: list[str]) -> list[str]:
    """Refuse a label map with negative values or off its image (reported with the other
    problems); warn about a label found in one subject only (returned)."""
    assert m.labels is not None
    found: dict[int, list[int]] = {}  # nonzero label value -> the label maps holding it
    for i in sorted(ok):
        item, what = m.labels[i], f"labels[{i}]"
        try:
            summary = label_summary(item)
        except InputError as exc:
            problems.append(f"{what}: {_reader_problem(exc, item)}")
            continue
        negative = [v for v in summary.values if v < 0]
        if negative:
            problems.append(
                f"{what}: {_shown(item)} holds negative label values "
                f"({', '.join(map(str, negative[:3]))}{', ...' if len(negative) > 3 else ''}): "
                "labels are 0 (background) and positive integers"
            )
            continue
        if i in images_ok and (off := _off_image_mm(m.images[i], item, summary)) is not None:
            problems.append(
                f"{what}: {_shown(item)} is not on images[{i}] {_shown(m.images[i])}: its "
                f"labelled voxels reach {off:.1f} mm outside that image (another resolution "
                "over the same field of view is fine; check its origin and direction)"
            )
            continue
        for v in summary.values:
            if v != 0:
                found.setdefault(v, []).append(i)
    return _single_subject_labels(m, found, len(ok))


def _single_subject_labels(m, found: dict[int, list[int]], n_maps: int) -> list[str]:
    """The warning (a list of 0 or 1 line) that labels are found in one subject only.

    A subject is one of ``subjects`` where the manifest names them, else one image. Such a
    label has no counterpart to overlap with: every pair with that subject counts it as a
    mismatch, lowering the overlap. It may be meant (a lesion), so it is not refused.
    """
    assert m.labels is not None
    subject = m.subjects if m.subjects is not None else tuple(range(m.n_images))
    if len({subject[i] for ids in found.values() for i in ids}) < 2 or n_maps < 2:
        return []
    alone = []
    for v in sorted(found):
        maps = found[v]
        if len({subject[i] for i in maps}) != 1:
            continue
        held = ", ".join(f"labels[{i}] {_shown(m.labels[i])}" for i in maps)
        if m.subjects is None:
            alone.append(f"label {v} is only in {held}")
        else:
            alone.append(f"label {v} is only in subject {m.subjects[maps[0]]!r} ({held})")
    if not alone:
        return []
    more = len(alone) - _LABELS_NAMED
    listed = "; ".join(alone[:_LABELS_NAMED]) + (f"; and {more} more" if more > 0 else "")
    return [
        f"{listed}: a label of one subject counts as a mismatch in every pair with that "
        "subject and lowers the overlap; remove it unless it is meant (a lesion, say)"
    ]


# ----------------------------------------------------------------------------- matching

_LISTED = 4  # unmatched images named in a message; the rest are counted


def order_as_in_manifest(
    paths: Sequence[str | os.PathLike], manifest, *, what: str = "images"
) -> list[int]:
    """Match image files given in any order (a shell glob's) to a manifest's images by path.

    Parameters
    ----------
    paths : sequence of path
        The images as given (relative to the current directory, or absolute).
    manifest : Manifest
        A manifest of image files (its ``source`` names it in messages).
    what : str
        What the paths were given as, for messages (``"--images"``).

    Returns
    -------
    list of int, length n_images
        For each of the manifest's images, in its order, the index in `paths` of the same
        file (paths compared after resolving links): ``[paths[k] for k in order]`` lists the
        files in the manifest's order, and with them its groups and subjects.

    Raises
    ------
    InputError
        The paths are not the manifest's images: one line naming each path given twice,
        each path the manifest does not list, and each manifest image not given (with its
        group, when the manifest has groups).
    """
    label = str(manifest.source) if manifest.source is not None else "the manifest"
    folder = manifest.source.parent if manifest.source is not None else Path.cwd()
    unmatched: dict[Path, list[int]] = {}  # a file the manifest lists twice is given twice
    for i, item in enumerate(manifest.images):
        unmatched.setdefault(Path(item).resolve(), []).append(i)
    order: dict[int, int] = {}
    problems = []
    for k, p in enumerate(paths):
        left = unmatched.get(Path(p).resolve())
        if left is None:
            problems.append(f"{p} is not one of its images")
        elif not left:
            problems.append(f"{p} is given more often than the manifest lists it")
        else:
            order[left.pop(0)] = k
    for i, item in enumerate(manifest.images):
        if i not in order:
            group = f" (group {manifest.groups[i]})" if manifest.groups is not None else ""
            problems.append(f"its images[{i}] {relative_path(item, folder)}{group} is not given")
    if problems:
        more = len(problems) - _LISTED
        listed = "; ".join(problems[:_LISTED]) + (f"; and {more} more" if more > 0 else "")
        raise InputError(f"{what} do not match the images of {label}: {listed}")
    return [order[i] for i in range(manifest.n_images)]
