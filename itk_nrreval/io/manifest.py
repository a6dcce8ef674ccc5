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
is computed per subject under each registration (:mod:`itk_nrreval.io._brain_masks`).

``subjects`` (optional) names, per image, the subject it shows, where a subject has several
images (its contrasts in ``groups``, or repeat scans). Subject-level confidence then leaves
out a subject with all its images; without it each image is a subject, and a manifest with
``groups`` gets no subject-level confidence (leaving out one contrast of a subject is not
leaving out a subject).

Every transform maps reference (fixed) points to image (moving) points. A chain is listed
in ANTs ``fwdtransforms`` order: ``[warp, affine]`` means image point = affine(warp(p)); see
:mod:`itk_nrreval.io.transforms`. Relative paths are relative to the manifest's folder. A
transform written by FSL, AFNI, FreeSurfer or NiftyReg is an entry naming its format,
``{file:, format:[, reference:][, moving:]}`` (the images default to the registration's
reference and the entry's image), converted into this convention when read
(:mod:`itk_nrreval.io._foreign_transforms`).

The same content may be given as a dict (:func:`load_manifest`), and there, wherever a path
is accepted, an object in memory is too, mixed freely with paths:

* images, labels, mask, masks, references: a ``SimpleITK.Image``, an ITK Python image, or a numpy
  array with its grid, ``{"array": a, "spacing": s, "origin": o, "direction": d}`` (numpy
  order ``(z, y, x)``; spacing and origin in ITK (x, y[, z]) order, mm, LPS; direction
  row-major; see :mod:`itk_nrreval.io._images`);
* transforms and ``frame_transform``: a ``SimpleITK.Transform`` of any kind (composites
  included), an ITK Python transform, or a displacement field as an image (any of the
  image forms above, one vector component per dimension, mm).

Each object is kept as an :class:`~itk_nrreval.io._images.InMemoryImage` /
:class:`~itk_nrreval.io.transforms.InMemoryTransform`: a private copy (later changes to the
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

Here: the manifest's types, loading (the structure, key by key) and writing. Each entry is
read and written by :mod:`itk_nrreval.io._manifest_entries`; the checks of the files and of what
the images hold are :mod:`itk_nrreval.io._manifest_files`.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import SimpleITK as sitk
import yaml

from .._errors import InputError
from .._output import write_text
from ._field_orientation import orientation_notes
from ._foreign_transforms import ForeignTransform
from ._images import InMemoryImage
from ._manifest_entries import (
    IDENTITY_FRAME,
    IN_MEMORY,
    chain_entry,
    groups_entry,
    image_entry,
    image_list,
    manifest_as_mapping,
    parameters_entry,
    per_image_labels,
    raise_problems,
)
from ._manifest_files import (
    MIN_IMAGES,
    check_image_contents,
    check_manifest_files,
    image_info,
    order_as_in_manifest,
)
from .label_names import label_names_from
from .transforms import FIELD_SUFFIXES, TRANSFORM_SUFFIXES, InMemoryTransform, transform_digest

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
        (:func:`itk_nrreval.measures.confidence.jackknife_groups`). None: each image is a subject.
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
        (:mod:`itk_nrreval.io._brain_masks`); None: no brain masks.
    label_names : dict of int to str, or None
        The labels' names (label value -> name), read from the manifest's ``label_names``
        (a ``dseg.tsv`` or FreeSurfer lookup table, or a mapping;
        :mod:`itk_nrreval.io.label_names`), shown beside the values; None: values only.
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
        return any(isinstance(item, IN_MEMORY) for item in items)

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
    if isinstance(item, (*IN_MEMORY, ForeignTransform)):
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
        label maps hold (:mod:`~itk_nrreval.io._manifest_files`: each image and label map read
        once, and kept, with the reader's checks, for the run that follows). False checks the
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
            notes = check_manifest_files(manifest, problems)
            if not problems:  # displacement fields that look like RAS given as LPS
                notes += orientation_notes(manifest)
    raise_problems(label, problems)
    assert manifest is not None
    for note in notes:
        warnings.warn(f"{label}: {note}", UserWarning, stacklevel=2)
    return replace(manifest, notes=tuple(notes)) if notes else manifest


def _parse(data: Mapping, base: Path, problems: list[str]) -> Manifest | None:
    for key in data:
        if key not in _TOP_KEYS:
            problems.append(f"unknown key {key!r} (expected {', '.join(_TOP_KEYS)})")
    images = None
    if "images" not in data:
        problems.append("missing 'images' (the list of N training images)")
    else:
        images = image_list(data["images"], base, "images", problems)
    labels = None
    if data.get("labels") is not None:
        labels = image_list(data["labels"], base, "labels", problems)
        if labels is not None and images is not None and len(labels) != len(images):
            problems.append(f"labels: {len(labels)} label maps for {len(images)} images")
    label_names = None
    if data.get("label_names") is not None:
        try:
            label_names = label_names_from(data["label_names"], base)
        except InputError as exc:
            problems.append(str(exc))
    mask = (
        image_entry(data["mask"], base, "mask", problems) if data.get("mask") is not None else None
    )
    n = None if images is None else len(images)
    groups = groups_entry(data["groups"], n, problems) if data.get("groups") is not None else None
    subjects = None
    if data.get("subjects") is not None:
        subjects = per_image_labels("subjects", data["subjects"], n, problems)
    evaluation_images = None
    if data.get("evaluation_images") is not None:
        what = "evaluation_images"
        evaluation_images = image_list(data[what], base, what, problems)
        if evaluation_images is not None and n is not None and len(evaluation_images) != n:
            problems.append(f"{what}: {len(evaluation_images)} images for {n} images")
    masks = None
    if data.get("masks") is not None:
        masks = image_list(data["masks"], base, "masks", problems)
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


def _identity_frame(reference, what: str, problems: list[str]) -> InMemoryTransform | None:
    """The identity transform of the reference's dimension, kept as ``identity``."""
    if reference is None:
        return None
    try:
        if isinstance(reference, InMemoryImage):
            dim = reference.image.GetDimension()
        else:
            dim = image_info(Path(reference))[0]
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
        reference = image_entry(entry["reference"], base, f"{where}.reference", problems)
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
                    chain_entry(
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
                chain = (chain_entry(item, base, w, problems, reference=reference, moving=moving),)
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
        frame = chain_entry(
            frame, base, f"{where}.frame_transform", problems, reference=None, moving=None
        )
        ok &= frame is not None
    parameters = entry.get("parameters")
    if parameters is not None:
        parameters = parameters_entry(parameters, where, problems)
        ok &= parameters is not None
    if not ok:
        return None
    return ManifestRegistration(reference, tuple(chains), ref_index, frame, parameters)


# ----------------------------------------------------------------------------- writing


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
    from .._version import __version__

    path = Path(path)
    m = load_manifest(manifest, check_files=False)
    folder = path.absolute().parent
    text = yaml.safe_dump(
        manifest_as_mapping(m, folder), sort_keys=False, default_flow_style=None, width=100
    )
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
        data = manifest_as_mapping(old, None)  # absolute paths
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
