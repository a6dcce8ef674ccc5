"""One entry of a manifest, read and written: a path (relative to the manifest's folder), an
image or transform given as an object, a transform in another tool's format, per-image labels,
a registration's recorded settings -- and the problems found, listed in one message.

:mod:`itk_nrreval.io.manifest` reads a manifest's mapping entry by entry with these (each
problem appended to a list, so that every problem is reported at once) and writes a
:class:`~itk_nrreval.io.manifest.Manifest` back as a mapping (:func:`manifest_as_mapping`; the
manifest is not annotated as one: that module imports this one).
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from .._errors import InputError
from ._foreign_transforms import ForeignTransform, entry_of, parse_entry
from ._images import InMemoryImage
from .transforms import InMemoryTransform

__all__ = [
    "IDENTITY_FRAME",
    "IN_MEMORY",
    "raise_problems",
    "image_entry",
    "image_list",
    "chain_entry",
    "per_image_labels",
    "groups_entry",
    "parameters_entry",
    "relative_path",
    "manifest_as_mapping",
]

IN_MEMORY = (InMemoryImage, InMemoryTransform)
"""The kinds of item a manifest holds for an image or transform given as an object."""


_PROBLEMS_LISTED = 10


def raise_problems(label: str, problems: list[str]) -> None:
    """Raise one InputError under `label` listing `problems` (the first ten, and how many
    more); nothing when there are none."""
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


def image_entry(value, base: Path, what: str, problems: list[str]):
    """A path, or an image object kept as an InMemoryImage named `what`."""
    return _item(InMemoryImage, value, base, what, problems)


def image_list(value, base: Path, what: str, problems: list[str]) -> tuple | None:
    """The images of a list under `what` (paths or objects, item i named ``what[i]``); None,
    with the problems added, when it is not a non-empty list or an item is bad."""
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
        problems.append(
            f"{what}: expected a list of file paths or images, got {type(value).__name__}"
        )
        return None
    if len(value) == 0:
        problems.append(f"{what}: the list is empty")
        return None
    out = [image_entry(v, base, f"{what}[{i}]", problems) for i, v in enumerate(value)]
    return None if any(p is None for p in out) else tuple(out)


def _transform_item(value, base: Path, what: str, problems: list[str]):
    """A path, or a transform / field object kept as an InMemoryTransform named `what`."""
    return _item(InMemoryTransform, value, base, what, problems)


def chain_entry(value, base: Path, what: str, problems: list[str], *, reference, moving):
    """One transform of a chain: a path, an object, or an entry naming its format
    (``{file: s01.mat, format: fsl[, reference: ...][, moving: ...]}``, kept as a
    :class:`~itk_nrreval.io._foreign_transforms.ForeignTransform`; `reference` and `moving` are
    its images' defaults)."""
    if isinstance(value, Mapping) and ("file" in value or "format" in value):
        return parse_entry(
            value,
            resolve=lambda v, w: image_entry(v, base, w, problems),
            what=what,
            problems=problems,
            reference=reference,
            moving=moving,
        )
    return _transform_item(value, base, what, problems)


def per_image_labels(key: str, value, n: int | None, problems: list[str]) -> tuple[str, ...] | None:
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


def groups_entry(value, n: int | None, problems: list[str]) -> tuple[str, ...] | None:
    """Each image's group label; every group has at least 2 images."""
    labels = per_image_labels("groups", value, n, problems)
    if labels is None:
        return None
    small = [g for g in dict.fromkeys(labels) if labels.count(g) < 2]
    if small:
        problems.append(f"groups: group {small[0]!r} has {labels.count(small[0])} image (needs 2)")
        return None
    return labels


def parameters_entry(value, where: str, problems: list[str]) -> dict | None:
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


def relative_path(path, folder: Path | None) -> str:
    """An item as a manifest file lists it: its path relative to `folder` (as given when
    `folder` is None or the path is relative), or ``identity``; an object cannot be written
    to a file (InputError)."""
    if isinstance(path, InMemoryTransform) and path.source == IDENTITY_FRAME:
        return IDENTITY_FRAME
    if isinstance(path, IN_MEMORY):
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


def _relative_transform(item, folder: Path | None):
    """A transform as a manifest writes it: a path, or an entry naming its format."""
    if isinstance(item, ForeignTransform):
        return entry_of(item, lambda p: relative_path(p, folder))
    return relative_path(item, folder)


def manifest_as_mapping(m, folder: Path | None) -> dict:
    """The mapping a manifest file holds for the manifest `m`, paths relative to `folder`
    (as held, absolute, when None): what :func:`itk_nrreval.io.manifest.load_manifest` reads
    back."""
    out: dict[str, Any] = {"images": [relative_path(p, folder) for p in m.images]}
    if m.labels is not None:
        out["labels"] = [relative_path(p, folder) for p in m.labels]
    if m.label_names is not None:
        out["label_names"] = {int(k): v for k, v in m.label_names.items()}
    if m.groups is not None:
        out["groups"] = list(m.groups)
    if m.subjects is not None:
        out["subjects"] = list(m.subjects)
    if m.evaluation_images is not None:
        out["evaluation_images"] = [relative_path(p, folder) for p in m.evaluation_images]
    if m.mask is not None:
        out["mask"] = relative_path(m.mask, folder)
    if m.masks is not None:
        out["masks"] = [relative_path(p, folder) for p in m.masks]
    out["common_frame"] = m.common_frame
    regs = {}
    for name, r in m.registrations.items():
        e: dict[str, Any] = {"reference": relative_path(r.reference, folder)}
        if r.reference_index is not None:
            e["reference_index"] = int(r.reference_index)
        if r.frame_transform is not None:
            e["frame_transform"] = _relative_transform(r.frame_transform, folder)
        e["transforms"] = [
            _relative_transform(c[0], folder)
            if len(c) == 1
            else [_relative_transform(t, folder) for t in c]
            for c in r.transforms
        ]
        if r.parameters is not None:
            e["parameters"] = dict(r.parameters)
        regs[name] = e
    out["registrations"] = regs
    return out
