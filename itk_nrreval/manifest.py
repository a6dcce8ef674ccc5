"""The manifest: N images, optional labels, and the registrations of them to evaluate.

A manifest is a YAML (or JSON) file::

    images: [img/s00.nii.gz, img/s01.nii.gz]        # N training images, each in its own space
    labels: [lab/s00.nii.gz, lab/s01.nii.gz]        # optional integer label maps, same spaces
    label_names: lab/dseg.tsv                        # optional: dseg.tsv, FreeSurfer LUT, {1: csf}
    groups: [t1, t1, t2, t2]                         # optional: each image's group (modality)
    subjects: [s00, s01, s00, s01]                   # optional: each image's subject
    evaluation_images: [img/s00_t2.nii.gz, img/s01_t2.nii.gz]  # optional: scored in their place
    mask: mask.nii.gz                                # optional, on the common frame's grid
    masks: [msk/s00.nii.gz, msk/s01.nii.gz]          # optional brain masks, on the images' grids
    common_frame: fluid                              # optional; default the first registration
    registrations:
      fluid:
        reference: fluid/template.nii.gz            # grid of this registration's frame
        transforms: [fluid/s00.h5, fluid/s01.h5]    # one entry per image: a path or a chain
        parameters: {smoothing_mm: 5}               # optional record of its settings
      pair1:
        reference: img/s01.nii.gz
        reference_index: 1                          # the reference is training image 1
        transforms: [[pair1/s00_1Warp.nii.gz, pair1/s00_0GenericAffine.mat], pair1/s01.tfm]
      groupwise:
        reference: group/mean.nii.gz
        frame_transform: group/common_to_group.h5   # common frame -> this frame (optional)
        transforms: [...]
      pipeline_v2:
        reference: v2/template.nii.gz
        frame_transform: identity     # the same template space as the common frame
        transforms: [...]
      flirt:
        reference: fluid/template.nii.gz
        transforms: [{file: flirt/s00.mat, format: fsl}, ...]  # another tool's format, named

``evaluation_images`` (optional) gives, per image, another scan of the same subject in the same
physical space -- another contrast or a repeat, not seen by the registration -- which is
resampled through the same transforms and scored in the image's place (the specificity,
the appearance and the per-subject scores; labels, transforms and plausibility are the
registration's own). Noise and bias that a registration fitted in the images it aligned do
not carry over to another scan, so rougher fields gain less from fitting them (the verdict's
known-truth benchmark, ``docs/verdict.md``, measures how much less).

``masks`` (optional) gives, per image, its brain mask (0 outside, 1 inside) on that image's
grid: each is brought into the common frame through its image's transform, and its Dice
with the common mask (``mask`` where given, else the majority vote of the subjects' masks)
is computed per subject under each registration (:mod:`itk_nrreval._brain_masks`).

``subjects`` (optional) names, per image, the subject it shows, where a subject has several
images (its contrasts in ``groups``, or repeat scans). Subject-level confidence then leaves
out a subject with all its images; without it each image is a subject, and a manifest with
``groups`` gets no subject-level confidence (leaving out one contrast of a subject is not
leaving out a subject).

Every transform maps reference (fixed) points to image (moving) points. A chain is listed
in ANTs ``fwdtransforms`` order: ``[warp, affine]`` means image point = affine(warp(p)); see
:mod:`itk_nrreval.transforms`. Relative paths are relative to the manifest's folder. A
transform written by FSL, AFNI, FreeSurfer or NiftyReg is an entry naming its format,
``{file:, format:[, reference:][, moving:]}`` (the images default to the registration's
reference and the entry's image), converted into this convention when read
(:mod:`itk_nrreval._foreign_transforms`).

The same content may be given as a dict (:func:`load_manifest`), and there, wherever a path
is accepted, an object in memory is too, mixed freely with paths:

* images, labels, mask, masks, references: a ``SimpleITK.Image``, an ITK Python image, or a numpy
  array with its grid, ``{"array": a, "spacing": s, "origin": o, "direction": d}`` (numpy
  order ``(z, y, x)``; spacing and origin in ITK (x, y[, z]) order, mm, LPS; direction
  row-major; see :mod:`itk_nrreval._images`);
* transforms and ``frame_transform``: a ``SimpleITK.Transform`` of any kind (composites
  included), an ITK Python transform, or a displacement field as an image (any of the
  image forms above, one vector component per dimension, mm).

Each object is kept as an :class:`~itk_nrreval._images.InMemoryImage` /
:class:`~itk_nrreval.transforms.InMemoryTransform`: a private copy (later changes to the
object do not reach the manifest), named after its place for messages
(``registrations.fluid.transforms[3]``), and keyed in the result cache by its content --
the key a file with the same content gets, so files and objects share cache entries.

:func:`load_manifest` checks everything that can be checked before the heavy work (keys,
counts, files present, image / transform dimensions, the ``common_frame`` name, and what the
images and label maps hold: an image listed twice, a constant image, NaN, label values, a
label map off its image) and reports every problem at once in one :class:`InputError`;
objects get the same checks and the same messages (the item named instead of the file).
:func:`write_manifest` writes paths relative to the manifest's folder (a manifest with
objects cannot be written);
:func:`add_registration` adds or replaces one registration in a manifest file, creating it
when needed.
"""

from __future__ import annotations

import json
import math
import os
import re
import warnings
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk
import yaml

from ._cache import content_digest
from ._elastix_files import (
    elastix_file_dimension,
    is_elastix_parameter_file,
    read_elastix_transform,
)
from ._errors import InputError
from ._executors import ITK_READ_LOCK
from ._field_orientation import orientation_notes
from ._foreign_transforms import ForeignTransform, entry_of, parse_entry, plain_field_problem
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
from ._output import write_text
from .label_names import label_names_from
from .transforms import (
    FIELD_SUFFIXES,
    TRANSFORM_SUFFIXES,
    InMemoryTransform,
    field_components_problem,
    file_suffix,
    transform_digest,
)

__all__ = [
    "ManifestRegistration",
    "Manifest",
    "load_manifest",
    "write_manifest",
    "written_by_nrreval",
    "check_rewritable",
    "WRITTEN_BY",
    "add_registration",
    "order_as_in_manifest",
    "TRANSFORM_SUFFIXES",
    "FIELD_SUFFIXES",
    "check_image_contents",
    "IDENTITY_FRAME",
    "MIN_IMAGES",
]


_TOP_KEYS = (
    "images",
    "labels",
    "label_names",
    "groups",
    "subjects",
    "evaluation_images",
    "mask",
    "masks",
    "common_frame",
    "registrations",
)
_REG_KEYS = ("reference", "transforms", "reference_index", "frame_transform", "parameters")

_ImageItem = "Path | InMemoryImage"
_TransformItem = "Path | InMemoryTransform"
_IN_MEMORY = (InMemoryImage, InMemoryTransform)


@dataclass(frozen=True)
class ManifestRegistration:
    """One registration as the manifest lists it: reference, transform chains, frame transform.

    What :func:`load_manifest` reads from a manifest's ``registrations``; the files (or
    in-memory objects) of the registration, not its scores.

    Attributes
    ----------
    reference : Path or InMemoryImage
        Image whose grid is this registration's reference frame (absolute path, or an
        image given in memory).
    transforms : tuple of tuple of (Path or InMemoryTransform), length n_images
        Per image, its chain in ANTs ``fwdtransforms`` order (a single transform is a chain
        of one). Each maps reference points (mm, LPS) to image points.
    reference_index : int or None
        Index k of the training image that is this registration's reference (pairwise
        registration to image k), or None.
    frame_transform : Path or InMemoryTransform or None
        A transform from the common frame into this registration's frame, or None.
    parameters : dict of str to value, or None
        The settings the registration was made with (e.g. a sweep's), recorded as given
        (JSON-ready: numbers, strings, booleans, lists of them); not used in the scoring.
    """

    reference: Any
    transforms: tuple[tuple[Any, ...], ...]
    reference_index: int | None = None
    frame_transform: Any = None
    parameters: Mapping[str, Any] | None = None


@dataclass(frozen=True)
class Manifest:
    """A parsed, checked manifest (all paths absolute).

    Attributes
    ----------
    images : tuple of (Path or InMemoryImage), length n_images
    labels : tuple of (Path or InMemoryImage), or None
    groups : tuple of str, or None
        Each image's group (e.g. its modality), in image order: specificity is then that of
        a mixture with one Gaussian per group (:func:`itk_nrreval.specificity`). Every group
        has at least 2 images.
    subjects : tuple of str, or None
        Each image's subject, in image order, where a subject has several images: the
        subject-level jackknife leaves out a subject with all its images
        (:func:`itk_nrreval.confidence.jackknife_groups`). None: each image is a subject.
    mask : Path or InMemoryImage or None
    common_frame : str
        Name of the registration whose reference frame is the common frame.
    registrations : dict of str to ManifestRegistration
        In the manifest's order.
    source : Path or None
        The manifest file, or None for a manifest built from a dict.
    evaluation_images : tuple of (Path or InMemoryImage), length n_images, or None
        Per image, another scan of the same subject in the same physical space, scored in
        the image's place (module docstring); None: the images themselves are scored.
    masks : tuple of (Path or InMemoryImage), length n_images, or None
        Per image, its brain mask on the image's own grid (values 0 and 1), brought into
        the common frame through the image's transforms for the per-subject mask Dice
        (:mod:`itk_nrreval._brain_masks`); None: no brain masks.
    label_names : dict of int to str, or None
        The labels' names (label value -> name), read from the manifest's ``label_names``
        (a ``dseg.tsv`` or FreeSurfer lookup table, or a mapping;
        :mod:`itk_nrreval.label_names`), shown beside the values; None: values only.
    notes : tuple of str
        The warnings the check gave, each also a ``UserWarning`` when the manifest was
        loaded (a label found in one subject only; displacement fields that look like RAS
        given as LPS), without the manifest's name; ``results.json`` keeps them
        (``options.manifest_warnings``).
    """

    images: tuple[Any, ...]
    labels: tuple[Any, ...] | None
    mask: Any
    common_frame: str
    registrations: Mapping[str, ManifestRegistration] = field(default_factory=dict)
    source: Path | None = None
    groups: tuple[str, ...] | None = None
    evaluation_images: tuple[Any, ...] | None = None
    subjects: tuple[str, ...] | None = None
    masks: tuple[Any, ...] | None = None
    label_names: Mapping[int, str] | None = None
    notes: tuple[str, ...] = ()

    @property
    def n_images(self) -> int:
        return len(self.images)

    @property
    def scored_images(self) -> tuple[Any, ...]:
        """The images whose voxels are scored: `evaluation_images` where given, else
        `images`."""
        return self.evaluation_images if self.evaluation_images is not None else self.images

    @property
    def names(self) -> tuple[str, ...]:
        """Registration names, in the manifest's order."""
        return tuple(self.registrations)

    @property
    def in_memory(self) -> bool:
        """Whether any image or transform was given as an object rather than a file."""
        items = [
            *self.images,
            *(self.labels or ()),
            *(self.evaluation_images or ()),
            *(self.masks or ()),
            self.mask,
        ]
        for r in self.registrations.values():
            items += [r.reference, r.frame_transform, *(t for c in r.transforms for t in c)]
        return any(isinstance(item, _IN_MEMORY) for item in items)

    @property
    def files(self) -> tuple[Path, ...]:
        """Every file the manifest reads (the manifest itself first, where it is a file):
        what an output folder must neither be nor hold."""
        items = [
            self.source,
            *self.images,
            *(self.labels or ()),
            *(self.evaluation_images or ()),
            *(self.masks or ()),
            self.mask,
        ]
        for r in self.registrations.values():
            items += [r.reference, r.frame_transform, *(t for c in r.transforms for t in c)]
            items += [  # the images a transform in another tool's format is read with
                getattr(t, k)
                for t in (r.frame_transform, *(t for c in r.transforms for t in c))
                if isinstance(t, ForeignTransform)
                for k in t.given
            ]
        return tuple(Path(item) for item in items if isinstance(item, (str, os.PathLike)))

    def describe(self) -> dict:
        """A JSON-ready description of the inputs (absolute paths; objects described by their
        manifest item, type and content digest)."""
        return {
            "manifest": None if self.source is None else str(self.source),
            "n_images": self.n_images,
            "images": [_describe_item(p) for p in self.images],
            "labels": None if self.labels is None else [_describe_item(p) for p in self.labels],
            "groups": None if self.groups is None else list(self.groups),
            "subjects": None if self.subjects is None else list(self.subjects),
            "evaluation_images": None
            if self.evaluation_images is None
            else [_describe_item(p) for p in self.evaluation_images],
            "mask": _describe_item(self.mask),
            "masks": None if self.masks is None else [_describe_item(p) for p in self.masks],
            **(
                {"label_names": {str(k): v for k, v in self.label_names.items()}}
                if self.label_names is not None
                else {}
            ),
            "common_frame": self.common_frame,
            "registrations": {
                name: {
                    "reference": _describe_item(r.reference),
                    "reference_index": r.reference_index,
                    "frame_transform": _describe_item(r.frame_transform),
                    "transforms": [[_describe_item(t) for t in chain] for chain in r.transforms],
                    "parameters": None if r.parameters is None else dict(r.parameters),
                }
                for name, r in self.registrations.items()
            },
        }


def _describe_item(item) -> Any:
    if item is None:
        return None
    if isinstance(item, (*_IN_MEMORY, ForeignTransform)):
        return item.describe()
    return str(item)


# ----------------------------------------------------------------------------- loading


def load_manifest(
    source: str | os.PathLike | Mapping,
    *,
    base_dir: str | os.PathLike | None = None,
    check_files: bool = True,
) -> Manifest:
    """Read and check a manifest, reporting every problem at once.

    Parameters
    ----------
    source : path or mapping
        A YAML / JSON manifest file, or the same content as a dict (a :class:`Manifest` is
        returned unchanged). In a dict, every image and transform may also be an object in
        memory (SimpleITK, ITK Python, an array with its grid; see the module docstring).
    base_dir : path, optional
        Folder that relative paths in a dict are relative to (default: the current
        directory). Ignored for a file: its paths are relative to its own folder.
    check_files : bool
        Also check that every file exists and that image and transform dimensions agree,
        files and objects alike (image headers, transform files), and what the images and
        label maps hold (:func:`_check_voxels`: each image and label map read once, and
        kept, with the reader's checks, for the run that follows). False checks the
        structure only (used when editing a manifest).

    Returns
    -------
    Manifest

    Raises
    ------
    InputError
        One message, ``"<manifest>: N problems: a; b; c"``, listing every problem found:
        unreadable YAML, unknown keys, missing files, objects of a kind not accepted, wrong
        counts, fewer than 3 images, dimensions that differ, a ``reference_index`` out of
        range, an unknown ``common_frame``; an image listed twice (the same file, or the
        same voxels on the same grid), a constant image, a NaN or infinite voxel value, a
        damaged NIfTI file, a label map with negative or non-integer values or off its
        image; a brain mask (``masks``) not on its image's grid, not binary, or empty.

    Warns
    -----
    UserWarning
        A label found in one subject's label map only (a lesion, say: it lowers the
        overlap of every pair with that subject). One line for all of them.
    """
    if isinstance(source, Manifest):
        return source
    if isinstance(source, Mapping):
        data = dict(source)
        base = Path(base_dir) if base_dir is not None else Path.cwd()
        label = "manifest"
        src_path = None
    else:
        src_path = Path(source).absolute()
        label = str(source)
        if src_path.is_dir():
            raise InputError(f"{label}: is a folder, expected a manifest file")
        if not src_path.is_file():
            raise InputError(f"{label}: manifest file not found")
        try:
            data = yaml.safe_load(src_path.read_text())
        except (yaml.YAMLError, UnicodeDecodeError) as exc:
            msg = " ".join(str(exc).split())
            raise InputError(f"{label}: not valid YAML/JSON ({msg[:200]})") from None
        if data is None:
            raise InputError(
                f"{label}: the manifest is empty (expected 'images' and 'registrations')"
            )
        if not isinstance(data, Mapping):
            raise InputError(f"{label}: expected a mapping with 'images' and 'registrations'")
        base = src_path.parent
    problems: list[str] = []
    notes: list[str] = []  # warnings, given only for a manifest that is not refused
    manifest = _parse(data, base.absolute(), problems)
    if manifest is not None:
        manifest = replace(manifest, source=src_path)
        if check_files:
            notes = _check_files(manifest, problems)
            if not problems:  # displacement fields that look like RAS given as LPS
                notes += orientation_notes(manifest)
    _raise(label, problems)
    assert manifest is not None
    for note in notes:
        warnings.warn(f"{label}: {note}", UserWarning, stacklevel=2)
    return replace(manifest, notes=tuple(notes)) if notes else manifest


_PROBLEMS_LISTED = 10


def _raise(label: str, problems: list[str]) -> None:
    if not problems:
        return
    if len(problems) == 1:
        raise InputError(f"{label}: {problems[0]}")
    # every problem is counted; a line naming hundreds (a list of bad entries) is unreadable
    listed = "; ".join(problems[:_PROBLEMS_LISTED])
    more = len(problems) - _PROBLEMS_LISTED
    if more > 0:
        listed += f"; and {more} more"
    raise InputError(f"{label}: {len(problems)} problems: {listed}")


def _path(value, base: Path, what: str, problems: list[str]) -> Path | None:
    if isinstance(value, (str, os.PathLike)) and str(value).strip():
        p = Path(os.path.expanduser(str(value)))
        return Path(os.path.normpath(p if p.is_absolute() else base / p))
    problems.append(f"{what}: expected a file path, got {value!r}")
    return None


def _item(kind, value, base: Path, what: str, problems: list[str]):
    """A path, or an object kept as `kind` (InMemoryImage or InMemoryTransform) named `what`."""
    if isinstance(value, kind):
        return value
    if value is None or isinstance(value, (str, bytes, os.PathLike, int, float)):
        return _path(value, base, what, problems)
    try:
        return kind.from_object(value, name=what)
    except InputError as exc:
        problems.append(str(exc))
        return None


def _image_item(value, base: Path, what: str, problems: list[str]):
    """A path, or an image object kept as an InMemoryImage named `what`."""
    return _item(InMemoryImage, value, base, what, problems)


def _path_list(value, base: Path, what: str, problems: list[str]) -> tuple | None:
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
        problems.append(
            f"{what}: expected a list of file paths or images, got {type(value).__name__}"
        )
        return None
    if len(value) == 0:
        problems.append(f"{what}: the list is empty")
        return None
    out = [_image_item(v, base, f"{what}[{i}]", problems) for i, v in enumerate(value)]
    return None if any(p is None for p in out) else tuple(out)


def _transform_item(value, base: Path, what: str, problems: list[str]):
    """A path, or a transform / field object kept as an InMemoryTransform named `what`."""
    return _item(InMemoryTransform, value, base, what, problems)


def _chain_item(value, base: Path, what: str, problems: list[str], *, reference, moving):
    """One transform of a chain: a path, an object, or an entry naming its format
    (``{file: s01.mat, format: fsl[, reference: ...][, moving: ...]}``, kept as a
    :class:`~itk_nrreval._foreign_transforms.ForeignTransform`; `reference` and `moving` are
    its images' defaults)."""
    if isinstance(value, Mapping) and ("file" in value or "format" in value):
        return parse_entry(
            value,
            resolve=lambda v, w: _image_item(v, base, w, problems),
            what=what,
            problems=problems,
            reference=reference,
            moving=moving,
        )
    return _transform_item(value, base, what, problems)


def _parse(data: Mapping, base: Path, problems: list[str]) -> Manifest | None:
    for key in data:
        if key not in _TOP_KEYS:
            problems.append(f"unknown key {key!r} (expected {', '.join(_TOP_KEYS)})")
    images = None
    if "images" not in data:
        problems.append("missing 'images' (the list of N training images)")
    else:
        images = _path_list(data["images"], base, "images", problems)
    labels = None
    if data.get("labels") is not None:
        labels = _path_list(data["labels"], base, "labels", problems)
        if labels is not None and images is not None and len(labels) != len(images):
            problems.append(f"labels: {len(labels)} label maps for {len(images)} images")
    label_names = None
    if data.get("label_names") is not None:
        try:
            label_names = label_names_from(data["label_names"], base)
        except InputError as exc:
            problems.append(str(exc))
    mask = (
        _image_item(data["mask"], base, "mask", problems) if data.get("mask") is not None else None
    )
    n = None if images is None else len(images)
    groups = _groups(data["groups"], n, problems) if data.get("groups") is not None else None
    subjects = None
    if data.get("subjects") is not None:
        subjects = _labels("subjects", data["subjects"], n, problems)
    evaluation_images = None
    if data.get("evaluation_images") is not None:
        what = "evaluation_images"
        evaluation_images = _path_list(data[what], base, what, problems)
        if evaluation_images is not None and n is not None and len(evaluation_images) != n:
            problems.append(f"{what}: {len(evaluation_images)} images for {n} images")
    masks = None
    if data.get("masks") is not None:
        masks = _path_list(data["masks"], base, "masks", problems)
        if masks is not None and n is not None and len(masks) != n:
            problems.append(f"masks: {len(masks)} brain masks for {n} images")
            masks = None  # which mask is whose is unknown: none is checked further

    regs: dict[str, ManifestRegistration] = {}
    raw = data.get("registrations")
    if raw is None:
        problems.append("missing 'registrations' (at least one)")
    elif not isinstance(raw, Mapping) or len(raw) == 0:
        problems.append("registrations: expected a non-empty mapping of name -> registration")
    else:
        for name, entry in raw.items():
            reg = _parse_registration(str(name), entry, base, n, problems, images=images)
            if reg is not None:
                regs[str(name)] = reg
    common = data.get("common_frame")
    if common is None:
        common = next(iter(raw)) if isinstance(raw, Mapping) and raw else ""
    elif isinstance(raw, Mapping) and str(common) not in {str(k) for k in raw}:
        problems.append(
            f"common_frame {common!r} is not a registration (have: {', '.join(map(str, raw))})"
        )
    if images is None:
        return None
    return Manifest(
        images,
        labels,
        mask,
        str(common),
        regs,
        groups=groups,
        evaluation_images=evaluation_images,
        subjects=subjects,
        masks=masks,
        label_names=label_names,
    )


def _labels(key: str, value, n: int | None, problems: list[str]) -> tuple[str, ...] | None:
    """One label per image under `key` (numbers and strings both become strings)."""
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
        problems.append(f"{key}: expected a list with one label per image")
        return None
    bad = [v for v in value if isinstance(v, bool) or not isinstance(v, (str, int))]
    if bad:
        problems.append(f"{key}: labels must be strings or integers, got {bad[0]!r}")
        return None
    labels = tuple(str(v) for v in value)
    if n is not None and len(labels) != n:
        problems.append(f"{key}: {len(labels)} labels for {n} images")
        return None
    return labels


def _groups(value, n: int | None, problems: list[str]) -> tuple[str, ...] | None:
    """Each image's group label; every group has at least 2 images."""
    labels = _labels("groups", value, n, problems)
    if labels is None:
        return None
    small = [g for g in dict.fromkeys(labels) if labels.count(g) < 2]
    if small:
        problems.append(f"groups: group {small[0]!r} has {labels.count(small[0])} image (needs 2)")
        return None
    return labels


def _parameters(value, where: str, problems: list[str]) -> dict | None:
    """A registration's recorded settings: a mapping of name to JSON-ready values."""
    if not isinstance(value, Mapping):
        problems.append(f"{where}.parameters: expected a mapping of setting name to value")
        return None
    try:
        return json.loads(json.dumps(dict(value)))
    except (TypeError, ValueError):
        problems.append(f"{where}.parameters: values must be numbers, strings, booleans or lists")
        return None


IDENTITY_FRAME = "identity"
"""``frame_transform: identity`` in a manifest: this registration's frame is the common
frame itself (its reference is on the same template grid, in the same space), so no frame
is estimated: e.g. two pipelines' outputs in one template space."""


def _identity_frame(reference, what: str, problems: list[str]) -> InMemoryTransform | None:
    """The identity transform of the reference's dimension, kept as ``identity``."""
    if reference is None:
        return None
    try:
        if isinstance(reference, InMemoryImage):
            dim = reference.image.GetDimension()
        else:
            dim = _image_info(Path(reference))[0]
    except (RuntimeError, OSError):
        return None  # the reference's own problem is reported by the file checks
    t = sitk.Transform(dim, sitk.sitkIdentity)
    return InMemoryTransform(t, what, IDENTITY_FRAME, transform_digest(t), True)


def _parse_registration(
    name: str, entry, base: Path, n: int | None, problems: list[str], *, images=None
) -> ManifestRegistration | None:
    where = f"registrations.{name}"
    if not isinstance(entry, Mapping):
        problems.append(f"{where}: expected a mapping with 'reference' and 'transforms'")
        return None
    for key in entry:
        if key not in _REG_KEYS:
            problems.append(f"{where}: unknown key {key!r} (expected {', '.join(_REG_KEYS)})")
    ok = True
    reference = None
    if "reference" not in entry:
        problems.append(f"{where}: missing 'reference' (the image whose grid is its frame)")
        ok = False
    else:
        reference = _image_item(entry["reference"], base, f"{where}.reference", problems)
        ok &= reference is not None
    chains: list[tuple] = []
    raw = entry.get("transforms")
    if raw is None:
        problems.append(f"{where}: missing 'transforms' (one per image)")
        ok = False
    elif isinstance(raw, (str, bytes)) or not isinstance(raw, Sequence):
        problems.append(f"{where}.transforms: expected a list, one entry per image")
        ok = False
    else:
        if n is not None and len(raw) != n:
            problems.append(f"{where}.transforms: {len(raw)} entries for {n} images")
            ok = False
        for i, item in enumerate(raw):
            w = f"{where}.transforms[{i}]"
            # an entry in another tool's format defaults its images to the registration's
            # reference (for the transform acting first) and this image (for the one acting last)
            moving = images[i] if images is not None and i < len(images) else None
            if isinstance(item, (list, tuple)):
                if len(item) == 0:
                    problems.append(f"{w}: empty chain")
                    ok = False
                    continue
                chain = tuple(
                    _chain_item(
                        t,
                        base,
                        f"{w}[{j}]",
                        problems,
                        reference=reference if j == 0 else None,
                        moving=moving if j == len(item) - 1 else None,
                    )
                    for j, t in enumerate(item)
                )
            else:
                chain = (_chain_item(item, base, w, problems, reference=reference, moving=moving),)
            ok &= all(t is not None for t in chain)
            chains.append(chain)
    ref_index = entry.get("reference_index")
    if ref_index is not None:
        if isinstance(ref_index, bool) or not isinstance(ref_index, int):
            problems.append(f"{where}.reference_index: expected an integer, got {ref_index!r}")
            ok = False
        elif n is not None and not 0 <= ref_index < n:
            problems.append(f"{where}.reference_index: {ref_index} is not in 0..{n - 1}")
            ok = False
    frame = entry.get("frame_transform")
    if isinstance(frame, str) and frame == IDENTITY_FRAME:
        frame = _identity_frame(reference, f"{where}.frame_transform", problems)
        ok &= frame is not None
    elif frame is not None:
        # an entry in another tool's format names both its images here: the common frame's
        # reference is another registration's
        frame = _chain_item(
            frame, base, f"{where}.frame_transform", problems, reference=None, moving=None
        )
        ok &= frame is not None
    parameters = entry.get("parameters")
    if parameters is not None:
        parameters = _parameters(parameters, where, problems)
        ok &= parameters is not None
    if not ok:
        return None
    return ManifestRegistration(reference, tuple(chains), ref_index, frame, parameters)


# ----------------------------------------------------------------------------- file checks


def _image_info(path: Path) -> tuple[int, int]:
    """(dimension, components) of an image from its header."""
    reader = read_header(path)
    return reader.GetDimension(), reader.GetNumberOfComponents()


_TEXT_HEADER = re.compile(r"^Transform:\s*\S+?_(\d)_(\d)\s*$")


def _transform_file_dimension(path: Path) -> int:
    """Spatial dimension of a transform file or displacement-field image, cheaply.

    Text transform files are scanned for their ``Transform: Name_double_D_D`` line (elastix
    parameter files are read with their initial transforms, cheap text); HDF5 files of
    composites, affine maps and displacement fields from their layout
    (:func:`_hdf5_transform_dimension`); other transform files are read whole;
    displacement-field images give their header's dimension.

    Raises
    ------
    RuntimeError, ValueError
        When the file cannot be read as a transform.
    """
    suffix = file_suffix(path)
    if suffix in FIELD_SUFFIXES:
        dim, comps = _image_info(path)
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
            d, comps = _image_info(item)
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


def _check_files(m: Manifest, problems: list[str]) -> list[str]:
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


def _check_masks_held(m: Manifest, ok: set[int], problems: list[str]) -> None:
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
    m: Manifest, images_ok: set[int], scored_ok: set[int], labels_ok: set[int], problems: list
) -> list[str]:
    """What the images and label maps hold, for those whose headers passed (the `_ok`
    indices): each is read once, before any heavy work, so that what would change the
    numbers without a word is refused with every other problem.

    Images and evaluation images (:func:`_check_images_held`): NaN or infinite values, a
    damaged NIfTI file, a constant image, an image listed twice. Label maps
    (:func:`_check_labels_held`): values that are not integers or are negative, a label map
    off its image; a label of one subject only is a warning (returned).

    Cost per image: a NIfTI file's slab-by-slab read (:func:`~itk_nrreval._images.voxel_range`)
    and ITK's read for its content digest (:func:`~itk_nrreval._cache.content_digest`), both
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


def _check_labels_held(
    m: Manifest, ok: set[int], images_ok: set[int], problems: list[str]
) -> list[str]:
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


def _single_subject_labels(m: Manifest, found: dict[int, list[int]], n_maps: int) -> list[str]:
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
    paths: Sequence[str | os.PathLike], manifest: Manifest, *, what: str = "images"
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
            problems.append(f"its images[{i}] {_rel(item, folder)}{group} is not given")
    if problems:
        more = len(problems) - _LISTED
        listed = "; ".join(problems[:_LISTED]) + (f"; and {more} more" if more > 0 else "")
        raise InputError(f"{what} do not match the images of {label}: {listed}")
    return [order[i] for i in range(manifest.n_images)]


# ----------------------------------------------------------------------------- writing


def _rel(path, folder: Path | None) -> str:
    if isinstance(path, InMemoryTransform) and path.source == IDENTITY_FRAME:
        return IDENTITY_FRAME
    if isinstance(path, _IN_MEMORY):
        raise InputError(
            f"manifest: {path.name} is an in-memory {path.source} and cannot be written to a "
            "manifest file; write it to a file first"
        )
    p = Path(path)
    if folder is None or not p.is_absolute():
        return p.as_posix()
    try:
        return Path(os.path.relpath(p, folder)).as_posix()
    except ValueError:  # another drive on Windows
        return p.as_posix()


def _rel_transform(item, folder: Path | None):
    """A transform as a manifest writes it: a path, or an entry naming its format."""
    if isinstance(item, ForeignTransform):
        return entry_of(item, lambda p: _rel(p, folder))
    return _rel(item, folder)


def _to_dict(m: Manifest, folder: Path | None) -> dict:
    out: dict[str, Any] = {"images": [_rel(p, folder) for p in m.images]}
    if m.labels is not None:
        out["labels"] = [_rel(p, folder) for p in m.labels]
    if m.label_names is not None:
        out["label_names"] = {int(k): v for k, v in m.label_names.items()}
    if m.groups is not None:
        out["groups"] = list(m.groups)
    if m.subjects is not None:
        out["subjects"] = list(m.subjects)
    if m.evaluation_images is not None:
        out["evaluation_images"] = [_rel(p, folder) for p in m.evaluation_images]
    if m.mask is not None:
        out["mask"] = _rel(m.mask, folder)
    if m.masks is not None:
        out["masks"] = [_rel(p, folder) for p in m.masks]
    out["common_frame"] = m.common_frame
    regs = {}
    for name, r in m.registrations.items():
        e: dict[str, Any] = {"reference": _rel(r.reference, folder)}
        if r.reference_index is not None:
            e["reference_index"] = int(r.reference_index)
        if r.frame_transform is not None:
            e["frame_transform"] = _rel_transform(r.frame_transform, folder)
        e["transforms"] = [
            _rel_transform(c[0], folder) if len(c) == 1 else [_rel_transform(t, folder) for t in c]
            for c in r.transforms
        ]
        if r.parameters is not None:
            e["parameters"] = dict(r.parameters)
        regs[name] = e
    out["registrations"] = regs
    return out


def write_manifest(manifest: Manifest | Mapping, path: str | os.PathLike) -> Path:
    """Write `manifest` as YAML to `path` atomically, paths relative to its folder.

    The first line is the comment :data:`WRITTEN_BY` and the version: a later run may
    replace the file (:func:`written_by_nrreval`); the caller decides whether `path` may be
    written (:func:`itk_nrreval._output.check_output_file`).

    Parameters
    ----------
    manifest : Manifest or mapping
        A mapping is parsed (structure only) with relative paths taken from the current
        directory.
    path : path
        The manifest file to write (its folder is created).

    Returns
    -------
    Path
        `path`.
    """
    from ._version import __version__

    path = Path(path)
    m = load_manifest(manifest, check_files=False)
    folder = path.absolute().parent
    text = yaml.safe_dump(_to_dict(m, folder), sort_keys=False, default_flow_style=None, width=100)
    write_text(path, f"{WRITTEN_BY} {__version__}\n{text}")
    return path


WRITTEN_BY = "# written by itk-nrreval"
"""The first line of every manifest :func:`write_manifest` writes (then the version): how
:func:`written_by_nrreval` tells the toolkit's manifests from a user's."""


def written_by_nrreval(path: str | os.PathLike) -> bool:
    """Whether the file at `path` is a manifest this toolkit wrote (its first line is
    :data:`WRITTEN_BY`, alone or followed by a version): one it may replace
    (:func:`itk_nrreval._output.check_output_file`'s `ours`)."""
    try:
        with open(path, encoding="utf-8") as fh:
            first = fh.readline().rstrip("\n")
    except (OSError, UnicodeDecodeError):
        return False
    return first == WRITTEN_BY or first.startswith(WRITTEN_BY + " ")


def check_rewritable(manifest_path: str | os.PathLike) -> None:
    """Refuse a manifest that adding a registration would rewrite but the toolkit did not
    write: its comments and layout would be lost.

    Raises
    ------
    InputError
        `manifest_path` exists and is not :func:`written_by_nrreval`.
    """
    if os.path.lexists(manifest_path) and not written_by_nrreval(manifest_path):
        raise InputError(
            f"{manifest_path}: a manifest nrreval did not write; adding the registration would "
            "rewrite it. Give a new manifest file (it may list the same images), or add the "
            "registration to it by hand (nothing was written)"
        )


def add_registration(
    manifest_path: str | os.PathLike,
    name: str,
    *,
    reference: str | os.PathLike,
    transforms: Sequence,
    reference_index: int | None = None,
    frame_transform: str | os.PathLike | None = None,
    images: Sequence[str | os.PathLike] | None = None,
    labels: Sequence[str | os.PathLike] | None = None,
    parameters: Mapping[str, Any] | None = None,
) -> Path:
    """Add (or replace) registration `name` in a manifest file, creating the file if needed.

    Parameters
    ----------
    manifest_path : path
        The manifest (YAML). Created when missing; then `images` is required.
    name : str
        Registration name; an existing registration of that name is replaced in place.
    reference : path
        Image whose grid is the registration's frame.
    transforms : sequence, one entry per image
        A path, or a chain of paths in ANTs ``fwdtransforms`` order, per image.
    reference_index, frame_transform : optional
        See :class:`ManifestRegistration`.
    images, labels : sequence of path, optional
        Set the manifest's images / labels (a new manifest needs `images`; for an existing
        one, given images must be the same files).
    parameters : mapping, optional
        The settings the registration was made with, recorded in the manifest.

    Paths given here that are relative are relative to the current directory (they are
    rewritten relative to the manifest's folder).

    Returns
    -------
    Path
        `manifest_path`.

    Raises
    ------
    InputError
        Bad structure (wrong counts ...), `images` differing from an existing manifest's,
        or an existing manifest the toolkit did not write (:func:`check_rewritable`).
    """
    manifest_path = Path(manifest_path)
    check_rewritable(manifest_path)
    cwd = Path.cwd()

    def absolute(p):
        if not isinstance(p, (str, os.PathLike)):
            raise InputError(
                f"{manifest_path}: a manifest file lists files; write the in-memory "
                f"{type(p).__name__} to a file first"
            )
        return cwd / Path(p)

    if manifest_path.exists():
        old = load_manifest(manifest_path, check_files=False)
        if images is not None:
            new_images = tuple(absolute(p).resolve() for p in images)
            if new_images != tuple(p.resolve() for p in old.images):
                raise InputError(
                    f"{manifest_path}: the images given differ from the manifest's images"
                )
        data = _to_dict(old, None)  # absolute paths
        if labels is not None:
            data["labels"] = [str(absolute(p)) for p in labels]
    else:
        if images is None:
            raise InputError(f"{manifest_path}: manifest does not exist; give images= to create it")
        data = {"images": [str(absolute(p)) for p in images]}
        if labels is not None:
            data["labels"] = [str(absolute(p)) for p in labels]
    entry: dict[str, Any] = {"reference": str(absolute(reference))}
    if reference_index is not None:
        entry["reference_index"] = reference_index
    if frame_transform is not None:
        entry["frame_transform"] = str(absolute(frame_transform))
    entry["transforms"] = [
        [str(absolute(t)) for t in item] if isinstance(item, (list, tuple)) else str(absolute(item))
        for item in transforms
    ]
    if parameters is not None:
        entry["parameters"] = dict(parameters)
    regs = dict(data.get("registrations") or {})
    regs[str(name)] = entry
    data["registrations"] = regs
    m = load_manifest(data, base_dir="/", check_files=False)
    m = replace(m, common_frame=data.get("common_frame") or m.common_frame)
    return write_manifest(m, manifest_path)
