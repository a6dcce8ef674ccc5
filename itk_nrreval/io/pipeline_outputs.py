"""Manifests from what pipelines already wrote: BIDS derivatives, ANTs prefixes, elastix folders.

**BIDS derivatives** (fMRIPrep, sMRIPrep, and any pipeline writing their layout):
:func:`manifest_from_derivatives` takes one folder per registration. In each, under
``sub-<label>/[ses-<label>/]anat/``, the files are found by their BIDS entities:

=========================================================  ==================================
``sub-<l>[_ses-<l>]_desc-preproc_T1w.nii.gz``              the image (no ``space`` entity)
``sub-<l>[_ses-<l>]_dseg.nii.gz``                          its labels (no ``space``, no
                                                           ``desc``: fMRIPrep's tissue classes)
``sub-<l>[_ses-<l>]_desc-brain_mask.nii.gz``               its brain mask (no ``space``: on
                                                           the T1w image's grid)
``sub-<l>[_ses-<l>]_from-T1w_to-<SPACE>_mode-image_xfm.h5``  the transform (``.h5`` or ``.txt``)
``sub-<l>[_ses-<l>]_space-<SPACE>_desc-preproc_T1w.nii.gz``  on the template's grid: the frame
=========================================================  ==================================

The ``from-T1w_to-<SPACE>`` transform maps template points to T1w points (ITK convention:
it resamples the T1w image into the template space), as every transform of a manifest does,
with the template as the reference. The folder's ``dataset_description.json`` must exist; its
``GeneratedBy`` (name and version) names the registration. The images and labels are the
first folder's; the T1w image of every other folder must lie on the same grid (its
transforms map into that T1w space). Subjects (and sessions) are matched across folders; a
subject missing from one folder is left out with a one-line warning. The per-subject brain
masks (``desc-brain_mask``, the first folder's, beside each T1w image) become the manifest's
``masks``, where every subject kept has one: each subject's mask is then compared, in the
template space, with the common mask (:mod:`itk_nrreval.io._brain_masks`). A manifest's
``mask`` is one image on the common grid: give it (``mask=``, e.g. the template's own brain
mask) where wanted; it is then also the common mask the subjects' masks are compared with.

**ANTs, elastix, FSL and NiftyReg** (:func:`manifest_from_transforms`): shell-style patterns,
where what the ``*`` (and ``?``) stand for is the subject's label, matched across the
patterns: ``images="img/sub-*_T1w.nii.gz"``, an ANTs output prefix ``"out/sub-*_"`` (its
``<prefix>1Warp.nii.gz`` and ``<prefix>0GenericAffine.mat``, listed as the chain
``[warp, affine]`` in ANTs ``fwdtransforms`` order, or ``<prefix>Composite.h5``), an elastix
output folder ``"out/sub-*/"`` (its last ``TransformParameters.<k>.txt``, which stands for the
whole chain of runs: :mod:`itk_nrreval.io._elastix_files`), an FSL or NiftyReg file
``"flirt/sub-*.mat"`` (one per subject, an entry ``{file:, format:}`` whose images are the
reference and the subject's image: :mod:`itk_nrreval.io._foreign_transforms`). The reference is
the fixed image every subject was registered to. The patterns are read by
:mod:`itk_nrreval.io._transform_patterns`.

A small entity parser is used rather than pybids: the layouts read here need a file name
split at ``_`` and ``-``, and pybids (with its SQL index and dependencies) would add seconds
of start-up and a heavy install for that.
"""

from __future__ import annotations

import json
import os
import re
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._errors import InputError
from ._images import read_header
from ._transform_patterns import (
    engines_of,
    matches,
    method_written,
    registrations_found,
    subject_label,
)
from .manifest import IDENTITY_FRAME, Manifest, load_manifest

__all__ = [
    "BidsName",
    "parse_bids_name",
    "manifest_from_derivatives",
    "manifest_from_transforms",
]

_IMAGE_EXTENSIONS = (".nii.gz", ".nii")
_XFM_EXTENSIONS = (".h5", ".txt")
_KEY_VALUE = re.compile(r"^([A-Za-z0-9]+)-([A-Za-z0-9+]+)$")
_SUFFIX = re.compile(r"^[A-Za-z0-9]+$")


@dataclass(frozen=True)
class BidsName:
    """A BIDS file name split into its parts.

    Attributes
    ----------
    entities : dict of str to str
        ``key -> label`` in the order of the name (``{"sub": "01", "desc": "preproc"}``).
    suffix : str
        ``T1w``, ``dseg``, ``xfm``, ...
    extension : str
        From the first dot: ``.nii.gz``, ``.h5``, ``.json``.
    """

    entities: Mapping[str, str]
    suffix: str
    extension: str


def parse_bids_name(name: str) -> BidsName | None:
    """``sub-01_ses-A_desc-preproc_T1w.nii.gz`` -> its entities, suffix and extension.

    Returns None for a name that is not ``sub-<label>[_key-<label>...]_<suffix><extension>``
    (a file the layout does not describe, ignored).
    """
    stem, dot, rest = name.partition(".")
    parts = stem.split("_")
    if len(parts) < 2 or not _SUFFIX.match(parts[-1]):
        return None
    entities: dict[str, str] = {}
    for part in parts[:-1]:
        m = _KEY_VALUE.match(part)
        if m is None or m.group(1) in entities:
            return None
        entities[m.group(1)] = m.group(2)
    if next(iter(entities)) != "sub":
        return None
    return BidsName(entities, parts[-1], dot + rest)


# ----------------------------------------------------------------------------- BIDS


_SubjectKey = tuple  # (subject label, session label or "")


def _key_name(key: _SubjectKey) -> str:
    return f"sub-{key[0]}" + (f"_ses-{key[1]}" if key[1] else "")


@dataclass
class _Folder:
    """What one derivatives folder holds, by subject (and session)."""

    root: Path
    name: str  # the registration's name
    generated_by: str
    t1w: dict  # _SubjectKey -> [Path]
    dseg: dict
    brain_mask: dict  # _SubjectKey -> [Path]: desc-brain_mask in the T1w image's space
    xfm: dict  # _SubjectKey -> {space: [Path]}
    space_images: dict  # space -> [(Path, BidsName)]


def _generated_by(root: Path) -> str:
    """``Name Version`` of the pipeline that wrote `root` (its dataset_description.json)."""
    description = root / "dataset_description.json"
    if not description.is_file():
        raise InputError(
            f"{description}: not found; a BIDS derivatives folder names its pipeline there"
        )
    try:
        data = json.loads(description.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"{description}: not valid JSON ({' '.join(str(exc).split())})") from None
    if not isinstance(data, dict):
        raise InputError(f"{description}: expected a JSON object")
    generated = data.get("GeneratedBy")
    entry = generated[0] if isinstance(generated, list) and generated else None
    if not isinstance(entry, dict):  # BIDS before 1.4 wrote PipelineDescription
        entry = data.get("PipelineDescription")
    if not isinstance(entry, dict) or not entry.get("Name"):
        return ""
    return " ".join(str(entry[k]) for k in ("Name", "Version") if entry.get(k))


#: Pipelines whose normalization to a template is one known method, in every version:
#: fMRIPrep and sMRIPrep register the T1w image with ANTs SyN (niworkflows'
#: RobustMNINormalization; its settings, ``t1w-mni_registration_*.json``, chain Rigid, Affine
#: and SyN). Their versions are settings of one method for the verdict.
_PIPELINE_FAMILIES = {"fmriprep": ("SyN", "ants"), "smriprep": ("SyN", "ants")}


def _pipeline_family(generated_by: str) -> dict[str, str]:
    """``{method, engine}`` of a known pipeline (``GeneratedBy`` name), else empty."""
    name = generated_by.split(" ", 1)[0].lower()
    if name not in _PIPELINE_FAMILIES:
        return {}
    method, engine = _PIPELINE_FAMILIES[name]
    return {"method": method, "engine": engine}


def _scan(root: Path) -> _Folder:
    generated_by = _generated_by(root)
    found = _Folder(root, "", generated_by, {}, {}, {}, {}, {})
    files = sorted([*root.glob("sub-*/anat/*"), *root.glob("sub-*/ses-*/anat/*")])
    for path in files:
        parsed = parse_bids_name(path.name)
        if parsed is None or not path.is_file():
            continue
        e, suffix, ext = parsed.entities, parsed.suffix, parsed.extension
        key = (e["sub"], e.get("ses", ""))
        native = "space" not in e
        if suffix == "T1w" and ext in _IMAGE_EXTENSIONS and e.get("desc") == "preproc":
            if native:
                found.t1w.setdefault(key, []).append(path)
            else:
                found.space_images.setdefault(e["space"], []).append((path, parsed))
        elif suffix == "dseg" and ext in _IMAGE_EXTENSIONS and native and "desc" not in e:
            found.dseg.setdefault(key, []).append(path)
        elif suffix == "mask" and ext in _IMAGE_EXTENSIONS and native and e.get("desc") == "brain":
            found.brain_mask.setdefault(key, []).append(path)
        elif (
            suffix == "xfm"
            and ext in _XFM_EXTENSIONS
            and e.get("from") == "T1w"
            and e.get("mode") == "image"
            and "to" in e
        ):
            found.xfm.setdefault(key, {}).setdefault(e["to"], []).append(path)
    return found


def _one(paths: list[Path], what: str) -> Path:
    if len(paths) > 1:
        raise InputError(
            f"{paths[0]}: two candidate {what} for one subject ({paths[0].name} and "
            f"{paths[1].name}); keep one"
        )
    return paths[0]


def _space(folders: list[_Folder], space: str | None) -> tuple[str, dict[str, str]]:
    """The template space's name and the extra entities its images must have
    (``MNI152NLin6Asym:res-2`` -> ``("MNI152NLin6Asym", {"res": "2"})``)."""
    if space is not None:
        name, *extra = space.split(":")
        entities = {}
        for item in extra:
            m = _KEY_VALUE.match(item)
            if m is None:
                raise InputError(f"--space {space}: expected SPACE or SPACE:key-label, e.g. res-2")
            entities[m.group(1)] = m.group(2)
        for f in folders:
            have = sorted({s for spaces in f.xfm.values() for s in spaces})
            if name not in have:
                raise InputError(
                    f"{f.root}: no from-T1w_to-{name}_mode-image_xfm transform "
                    f"(it has: {', '.join(have) or 'none'})"
                )
        return name, entities
    for f in folders:
        have = sorted({s for spaces in f.xfm.values() for s in spaces})
        if not have:
            raise InputError(
                f"{f.root}: no sub-<label>[_ses-<label>]_from-T1w_to-<space>_mode-image_xfm "
                "transform under sub-*/[ses-*/]anat/"
            )
        if len(have) > 1:
            raise InputError(
                f"{f.root}: transforms into more than one space ({', '.join(have)}); choose one "
                "with --space"
            )
    spaces = sorted({s for f in folders for spaces in f.xfm.values() for s in spaces})
    if len(spaces) > 1:
        raise InputError(
            f"the folders' transforms go into different spaces ({', '.join(spaces)}); choose "
            "one with --space"
        )
    return spaces[0], {}


def _registered(f: _Folder, space: str) -> dict[_SubjectKey, Path]:
    """Subject -> its transform into `space`; every transform's T1w image checked present."""
    out = {}
    for key, spaces in sorted(f.xfm.items()):
        if space not in spaces:
            continue
        xfm = _one(spaces[space], f"transforms into {space}")
        if key not in f.t1w:
            raise InputError(
                f"{xfm}: a transform without its T1w image (no {_key_name(key)}"
                "_desc-preproc_T1w.nii.gz beside it)"
            )
        _one(f.t1w[key], "desc-preproc T1w images")
        out[key] = xfm
    return out


def _grid(path: Path) -> tuple:
    try:
        reader = read_header(path)
    except RuntimeError:
        raise InputError(f"{path}: cannot read image") from None
    return (
        reader.GetSize(),
        np.array(reader.GetSpacing()),
        np.array(reader.GetOrigin()),
        np.array(reader.GetDirection()),
    )


def _same_grid(a: tuple, b: tuple) -> bool:
    """Same size, and spacing, origin and direction within 1e-4 (mm, or of a cosine)."""
    return a[0] == b[0] and all(
        np.allclose(x, y, rtol=0, atol=1e-4) for x, y in zip(a[1:], b[1:], strict=True)
    )


def _names(folders: list[_Folder]) -> list[str]:
    """Each folder's registration name: its pipeline and version, or the folder's name where
    those do not tell it apart (or are not given); characters outside ``A-Za-z0-9._+-`` become
    ``-`` (the name also names result folders)."""

    def clean(text: str) -> str:
        return re.sub(r"[^A-Za-z0-9._+-]+", "-", text).strip("-")

    by = [clean(f.generated_by) for f in folders]
    names = [
        b if b and by.count(b) == 1 else clean(f"{b}_{f.root.name}" if b else f.root.name)
        for b, f in zip(by, folders, strict=True)
    ]
    for n, f in zip(names, folders, strict=True):
        if names.count(n) > 1:
            raise InputError(
                f"{f.root}: its pipeline, version and folder name are another folder's too "
                f"({n}); rename one folder"
            )
    return names


def manifest_from_derivatives(
    folders: Sequence[str | os.PathLike],
    *,
    space: str | None = None,
    mask: str | os.PathLike | None = None,
) -> Manifest:
    """A manifest of BIDS derivatives folders: one registration per folder.

    Parameters
    ----------
    folders : sequence of path
        BIDS derivatives folders (each with its ``dataset_description.json``); the layout
        read is in the module docstring.
    space : str, optional
        The template space (``MNI152NLin2009cAsym``), optionally with the entities that pick
        its images (``MNI152NLin6Asym:res-2``); default: the one space every folder's
        transforms go into.
    mask : path, optional
        A mask on the template's grid (also the common mask the subjects' brain masks are
        compared with).

    Returns
    -------
    Manifest
        Images (and labels, where every subject kept has a ``dseg``; brain masks, where
        every one has a ``desc-brain_mask``) of the first folder, subjects in label order
        (then session); per folder a registration named after its ``GeneratedBy`` whose
        reference is a ``space-<SPACE>`` image and whose parameters record the pipeline,
        folder and space (and, for fMRIPrep and sMRIPrep, whose normalization is ANTs SyN,
        ``method: SyN`` and ``engine: ants``: the verdict's family). The first folder's is
        the common frame; the others are in the same template space (``frame_transform:
        identity``), so no frame is estimated.

    Raises
    ------
    InputError
        Naming the file or folder: no ``dataset_description.json``, transforms into more
        than one space and no `space`, two candidate transforms (or T1w images) for one
        subject, a transform without its T1w image, no ``space-<SPACE>`` image, template
        images on different grids, a T1w image on another grid than the first folder's, no
        subject in every folder.

    Warns
    -----
    UserWarning
        One line per subject left out (missing from a folder), when labels are left out, and
        when brain masks are left out (some subjects have one, not every one).
    """
    if not folders:
        raise InputError("no derivatives folder given")
    roots = [Path(f).absolute() for f in folders]
    for root in roots:
        if not root.is_dir():
            raise InputError(f"{root}: not a folder")
    scanned = [_scan(root) for root in roots]
    for f, name in zip(scanned, _names(scanned), strict=True):
        f.name = name
    space_name, space_entities = _space(scanned, space)
    registered = [_registered(f, space_name) for f in scanned]
    kept = _subjects_in_every_folder(scanned, registered, space_name)
    first = scanned[0]
    images = _t1w_images(scanned, kept)
    labels = None
    no_dseg = [k for k in kept if k not in first.dseg]
    if no_dseg:
        warnings.warn(
            f"{first.root}: labels left out ({_key_name(no_dseg[0])} has no _dseg image)",
            stacklevel=2,
        )
    else:
        labels = [_one(first.dseg[k], "dseg label maps") for k in kept]
    masks = _brain_masks(first, kept)

    references = _references(scanned, kept, space_name, space_entities)
    data = {
        "images": [str(p) for p in images],
        **({"labels": [str(p) for p in labels]} if labels else {}),
        **({"label_names": str(n)} if labels and (n := _dseg_names(first.root, labels)) else {}),
        **({"masks": [str(p) for p in masks]} if masks else {}),
        # a subject's sessions are one subject: the jackknife leaves them out together
        **({"subjects": [f"sub-{k[0]}" for k in kept]} if any(k[1] for k in kept) else {}),
        **({"mask": str(Path(mask).absolute())} if mask is not None else {}),
        # every folder's template images are on one grid in one space (checked by
        # _references): the frames are the same
        "registrations": _in_one_frame(
            {
                f.name: {
                    "reference": str(ref),
                    "transforms": [str(r[k]) for k in kept],
                    "parameters": {
                        "generated_by": f.generated_by or None,
                        "folder": str(f.root),
                        "space": space_name,
                        **_pipeline_family(f.generated_by),
                    },
                }
                for f, r, ref in zip(scanned, registered, references, strict=True)
            }
        ),
    }
    return load_manifest(data)


def _subjects_in_every_folder(
    scanned: list[_Folder], registered: list[dict[_SubjectKey, Path]], space_name: str
) -> list[_SubjectKey]:
    """The subjects (and sessions) with a transform into the space in every folder, in
    order; each one left out is warned about, as a warning of the caller's caller."""
    keys = sorted(set().union(*registered))
    kept = [k for k in keys if all(k in r for r in registered)]
    for key in keys:
        if key not in kept:
            missing = [
                str(f.root) for f, r in zip(scanned, registered, strict=True) if key not in r
            ]
            warnings.warn(
                f"{_key_name(key)}: no transform into {space_name} in {', '.join(missing)}; "
                "left out",
                stacklevel=3,
            )
    if not kept:
        raise InputError(f"no subject has a transform into {space_name} in every folder")
    return kept


def _t1w_images(scanned: list[_Folder], kept: list[_SubjectKey]) -> list[Path]:
    """The first folder's T1w image of each kept subject, once every other folder's is
    checked to be on the same grid (the folders' transforms map into the same T1w spaces)."""
    first = scanned[0]
    images = [first.t1w[k][0] for k in kept]
    grids = {k: _grid(p) for k, p in zip(kept, images, strict=True)}
    for f in scanned[1:]:
        for key in kept:
            own = f.t1w[key][0]
            if not _same_grid(_grid(own), grids[key]):
                raise InputError(
                    f"{own}: not on the grid of {first.t1w[key][0]} (the folders' transforms "
                    "map into different T1w spaces)"
                )
    return images


def _dseg_names(root: Path, labels: list[Path]) -> Path | None:
    """The labels' names: a ``_dseg.tsv`` beside the first label map, else one
    ``[desc-<l>_]dseg.tsv`` at the dataset's root; None when there is none (or several)."""
    beside = labels[0].with_name(labels[0].name.split(".", 1)[0] + ".tsv")
    if beside.is_file():
        return beside
    at_root = sorted({*root.glob("desc-*_dseg.tsv"), *root.glob("dseg.tsv")})
    return at_root[0] if len(at_root) == 1 else None


def _brain_masks(folder: _Folder, kept: list[_SubjectKey]) -> list[Path] | None:
    """Each kept subject's ``desc-brain_mask`` image beside its T1w image, in `kept`'s order;
    None when a subject has none (one-line warning, unless no subject has one: a pipeline
    that writes no masks)."""
    lacking = [k for k in kept if k not in folder.brain_mask]
    if not lacking:
        return [_one(folder.brain_mask[k], "desc-brain_mask images") for k in kept]
    if len(lacking) < len(kept):
        warnings.warn(
            f"{folder.root}: brain masks left out ({_key_name(lacking[0])} has no "
            "_desc-brain_mask image)",
            stacklevel=3,
        )
    return None


def _in_one_frame(registrations: dict[str, dict]) -> dict[str, dict]:
    """Manifest entries of registrations whose references lie in one space on one grid: the
    first is the common frame, and every other one's frame is that frame itself
    (``frame_transform: identity``), not to be estimated.

    An estimate of a frame that is the common frame can only be worse than the identity:
    its error would change the scores of a registration that is not at fault.

    Parameters
    ----------
    registrations : dict
        Name -> entry (``reference``, ``transforms``, ...), the common frame first; the
        caller has made sure the references share the space and the grid (one file, or
        images on the same grid).

    Returns
    -------
    dict
        The entries, every one after the first with ``frame_transform: identity``.
    """
    return {
        name: {**entry, "frame_transform": IDENTITY_FRAME} if i > 0 else entry
        for i, (name, entry) in enumerate(registrations.items())
    }


def _references(
    folders: list[_Folder], kept: list[_SubjectKey], space: str, entities: dict[str, str]
) -> list[Path]:
    """Per folder, its first kept subject's ``space-<SPACE>`` image; every such image of the
    kept subjects on one grid."""
    references, seen = [], None
    for f in folders:
        images = [
            (p, n)
            for p, n in f.space_images.get(space, [])
            if (n.entities["sub"], n.entities.get("ses", "")) in kept
            and all(n.entities.get(k) == v for k, v in entities.items())
        ]
        if not images:
            which = ":".join([space, *(f"{k}-{v}" for k, v in entities.items())])
            raise InputError(
                f"{f.root}: no space-{space}_desc-preproc_T1w image of the subjects kept "
                f"(space {which}) to give the template's grid"
            )
        for path, _ in images:
            grid = _grid(path)
            if seen is None:
                seen = (path, grid)
            elif not _same_grid(grid, seen[1]):
                raise InputError(
                    f"{path}: not on the grid of {seen[0]} (the template's images differ; "
                    f"choose one resolution with --space {space}:res-<label>)"
                )
        references.append(images[0][0])
    return references


# ----------------------------------------------------------------------------- ANTs, elastix


def manifest_from_transforms(
    *,
    images: str,
    reference: str | os.PathLike,
    ants: Mapping[str, str] | Sequence[str] | str | None = None,
    elastix: Mapping[str, str] | Sequence[str] | str | None = None,
    fsl: Mapping[str, str] | Sequence[str] | str | None = None,
    niftyreg: Mapping[str, str] | Sequence[str] | str | None = None,
    labels: str | None = None,
    mask: str | os.PathLike | None = None,
    methods: Mapping[str, str] | None = None,
) -> Manifest:
    """A manifest of registrations written by antsRegistration, elastix, FSL and NiftyReg,
    matched by subject.

    Parameters
    ----------
    images : str, keyword-only
        Shell pattern of the images (``"img/sub-*_T1w.nii.gz"``): what its wildcards match is
        each subject's label.
    reference : path, keyword-only
        The fixed image every subject was registered to (its grid is the frame).
    ants : mapping of name to pattern, or pattern(s), keyword-only
        ANTs output prefixes (``"out/sub-*_"``); unnamed ones are named ``ants``, ``ants-2``...
    elastix : mapping of name to pattern, or pattern(s), keyword-only
        elastix output folders (``"out/sub-*/"``); unnamed: ``elastix``, ``elastix-2``...
    fsl : mapping of name to pattern, or pattern(s), keyword-only
        FSL transform files, one per subject (``"flirt/sub-*.mat"``: FLIRT matrices computed
        with ``-ref`` the reference and ``-in`` the subject's image; or FNIRT coefficient or
        displacement files), each an entry ``{file:, format: fsl}``; unnamed: ``fsl``...
    niftyreg : mapping of name to pattern, or pattern(s), keyword-only
        NiftyReg files, one per subject (``"nr/sub-*_aff.txt"``: reg_aladin's ``-aff``; or
        ``reg_transform -def`` / ``-disp`` fields), entries ``{file:, format: niftyreg}``;
        unnamed: ``niftyreg``...
    labels : str, optional, keyword-only
        Shell pattern of the label maps, matched to the images by subject label.
    mask : path, optional, keyword-only
        A mask on the reference's grid.
    methods : mapping of name to str, optional, keyword-only
        Registration name -> its method (``{"syn": "SyN"}``), where its files do not say it
        or say it wrongly: recorded as given.

    Returns
    -------
    Manifest
        Subjects in label order; registrations in the order given (ANTs, elastix, FSL,
        NiftyReg); the first is
        the common frame, and the others, registered to the same reference, are in it
        (``frame_transform: identity``), so no frame is estimated. Each registration's
        ``parameters`` give its ``engine`` (the tool whose files it reads) and, where its
        files name one (:func:`~itk_nrreval.io._transform_patterns.method_written`: an
        elastix ``Transform``, FLIRT, FNIRT coefficients, reg_aladin, an ANTs chain without
        a warp) or `methods` gives it, its ``method``: the verdict weighs roughness against
        specificity only between registrations of one method and engine.

    Raises
    ------
    InputError
        Naming the file: no image matches, a transform without its image, two candidate
        transforms for one subject, an elastix folder holding two chains; a method given
        for no registration of that name.

    Warns
    -----
    UserWarning
        One line per subject left out (no transform in one registration), and when labels
        are left out (a subject has none).
    """
    found = matches(images, what="--images")
    if not found:
        raise InputError(f"--images {images}: no file matches")
    image_of = {k: v[0][0] for k, v in found.items()}
    registrations = registrations_found(
        image_of, ants=ants, elastix=elastix, fsl=fsl, niftyreg=niftyreg
    )
    methods = dict(methods or {})
    for name in methods:
        if name not in registrations:
            raise InputError(
                f"--method {name}={methods[name]}: no registration named {name!r} (there are "
                f"{', '.join(registrations)})"
            )
    engines = engines_of(ants=ants, elastix=elastix, fsl=fsl, niftyreg=niftyreg)
    kept = _subjects_in_every_registration(image_of, registrations)
    label_files = None
    if labels is not None:
        label_of = {k: v[0][0] for k, v in matches(labels, what="--labels").items()}
        lacking = [k for k in kept if k not in label_of]
        if lacking:
            warnings.warn(
                f"--labels {labels}: labels left out (no label map for subject "
                f"{subject_label(lacking[0])})",
                stacklevel=2,
            )
        else:
            label_files = [str(label_of[k]) for k in kept]
    data = {
        "images": [str(image_of[k]) for k in kept],
        **({"labels": label_files} if label_files else {}),
        **({"mask": str(Path(mask).absolute())} if mask is not None else {}),
        # every subject was registered to the one reference: every registration's frame
        # is the first one's
        "registrations": _in_one_frame(
            {
                name: {
                    "reference": str(Path(reference).absolute()),
                    "transforms": [
                        [p if isinstance(p, Mapping) else str(p) for p in chains[k]] for k in kept
                    ],
                    "parameters": _family(
                        engines[name], {k: chains[k] for k in kept}, methods.get(name)
                    ),
                }
                for name, chains in registrations.items()
            }
        ),
    }
    return load_manifest(data)


def _family(engine: str, chains: dict[tuple, list], method: str | None) -> dict[str, str]:
    """A registration's ``parameters``: its engine, and its method where given or where its
    files name one."""
    method = method if method is not None else method_written(engine, chains)
    return {"engine": engine, **({"method": method} if method is not None else {})}


def _subjects_in_every_registration(
    image_of: dict[tuple, Path], registrations: dict[str, dict[tuple, list[Path]]]
) -> list[tuple]:
    """The subjects with a transform in every registration, in label order; each one left
    out is warned about, as a warning of the caller's caller."""
    kept = sorted(image_of)
    for key in list(kept):
        missing = [n for n, chains in registrations.items() if key not in chains]
        if missing:
            warnings.warn(
                f"{image_of[key]}: no transform in {', '.join(missing)}; left out", stacklevel=3
            )
            kept.remove(key)
    if not kept:
        raise InputError("no subject has a transform in every registration")
    return kept
