"""elastix's transform parameter files (``TransformParameters.<k>.txt``) read as ITK transforms.

elastix writes one text file per run of a registration: ``(Key value ...)`` lines naming the
transform (``(Transform "BSplineTransform")``), its parameters and, under
``InitialTransformParameterFileName`` (``...ParametersFileName`` before elastix 5.1), the file
of the run it started from, or ``"NoInitialTransform"``. The file of the last run therefore
stands for the whole registration: ``T_k(T_(k-1)(...T_0(p)))`` (elastix's
``HowToCombineTransforms "Compose"``: the initial transform acts first), mapping fixed
(reference) points to moving (image) points in mm, LPS -- the convention of every transform
in a manifest. Reading it here, with SimpleITK, avoids loading itk-elastix (about 10 s and
1 GB) to evaluate its results.

elastix records the initial file's path as it was given when it ran (often relative to that
run's working directory, ``out/sub-01/TransformParameters.0.txt``), so the path is looked for
as written when absolute, then relative to the file's own folder, then by its name in the
file's own folder (where elastix writes every run of one registration).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import SimpleITK as sitk

from .._errors import InputError

__all__ = [
    "ELASTIX_TRANSFORMS",
    "is_elastix_parameter_file",
    "read_parameter_file",
    "read_elastix_transform",
    "elastix_file_dimension",
    "bspline_from_parameter_map",
    "final_parameter_file",
]

ELASTIX_TRANSFORMS = (
    "TranslationTransform",
    "EulerTransform",
    "SimilarityTransform",
    "AffineTransform",
    "BSplineTransform",
    "RecursiveBSplineTransform",
)
"""The elastix transforms read here (elastix's names, as in its ``Transform`` entry)."""

_NO_INITIAL = "NoInitialTransform"
_INITIAL_KEYS = ("InitialTransformParameterFileName", "InitialTransformParametersFileName")
_ENTRY = re.compile(r"^\((\w+)\s*(.*)\)$")
_VALUE = re.compile(r'"([^"]*)"|(\S+)')
_RUN_FILE = re.compile(r"^TransformParameters\.(\d+)\.txt$")


def is_elastix_parameter_file(path: str | os.PathLike) -> bool:
    """Whether `path` is an elastix parameter file: a ``.txt`` file whose first line that is
    neither blank nor a ``//`` comment is a ``(Key value)`` entry (an ITK text transform file
    starts with ``#Insight Transform File``)."""
    path = Path(path)
    if path.suffix.lower() != ".txt" or not path.is_file():
        return False
    try:
        with open(path, errors="replace") as fh:
            for line in fh:
                line = line.strip()
                if line and not line.startswith("//"):
                    return line.startswith("(")
    except OSError:
        return False
    return False


def read_parameter_file(path: str | os.PathLike) -> dict[str, list[str]]:
    """The entries of an elastix parameter file: key -> its values, as text (quotes removed).

    Raises
    ------
    InputError
        The file cannot be read, or a line is neither blank, a ``//`` comment nor a
        ``(Key value ...)`` entry (the message gives the line number).
    """
    path = Path(path)
    try:
        text = path.read_text(errors="replace")
    except OSError as exc:
        raise InputError(f"{path}: cannot read elastix parameter file ({exc.strerror})") from None
    entries: dict[str, list[str]] = {}
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("//", 1)[0].strip()
        if not line:
            continue
        m = _ENTRY.match(line)
        if m is None:
            raise InputError(
                f"{path}: line {number} is not an elastix '(Key value ...)' entry: {line[:60]!r}"
            )
        values = _VALUE.finditer(m.group(2))
        entries[m.group(1)] = [v.group(1) if v.group(1) is not None else v.group(2) for v in values]
    return entries


def elastix_file_dimension(path: str | os.PathLike) -> int:
    """The spatial dimension of an elastix parameter file (its ``FixedImageDimension``).

    Raises
    ------
    InputError
        Unreadable file, or no valid ``FixedImageDimension`` entry.
    """
    pm = read_parameter_file(path)
    try:
        return int(pm["FixedImageDimension"][0])
    except (KeyError, IndexError, ValueError):
        raise InputError(f"{path}: elastix parameter file without FixedImageDimension") from None


def read_elastix_transform(path: str | os.PathLike) -> sitk.Transform:
    """The whole transform an elastix parameter file stands for, its initial ones included.

    Parameters
    ----------
    path : path
        ``TransformParameters.<k>.txt`` (module docstring for how initial files are found).

    Returns
    -------
    sitk.Transform
        The file's transform alone when it has no initial transform; otherwise a flat
        ``sitk.CompositeTransform([T_k, ..., T_0])`` (SimpleITK applies its list from the
        back, so T_0 acts first). Maps fixed points to moving points (mm, LPS).

    Raises
    ------
    InputError
        Naming the file: unreadable, a transform kind not in :data:`ELASTIX_TRANSFORMS`, a
        combination other than ``"Compose"``, parameters that do not fit the transform, or
        an initial transform file that cannot be found (or a chain that loops).
    """
    chain: list[sitk.Transform] = []
    seen: list[Path] = []
    current: Path | None = Path(path).absolute()
    while current is not None:
        if current in seen:
            raise InputError(f"{seen[0]}: its initial transforms loop back to {current}")
        seen.append(current)
        if not current.is_file():
            raise InputError(f"{current}: elastix parameter file not found")
        pm = read_parameter_file(current)
        chain.append(_one_transform(pm, current))
        current = _initial_file(pm, current)
    if len(chain) == 1:
        return chain[0]
    return sitk.CompositeTransform(chain)  # [T_k, ..., T_0]: T_0 acts first


def _initial_file(pm: dict[str, list[str]], path: Path) -> Path | None:
    """The initial transform file named in `pm` (read from `path`), or None."""
    key = next((k for k in _INITIAL_KEYS if k in pm), None)
    if key is None or not pm[key] or pm[key][0] == _NO_INITIAL:
        return None
    written = Path(pm[key][0])
    candidates = [written] if written.is_absolute() else [path.parent / written]
    candidates.append(path.parent / written.name)
    for candidate in candidates:
        if candidate.is_file():
            return candidate.absolute()
    raise InputError(
        f"{path}: its initial transform {written} was not found (looked as written and in "
        f"{path.parent})"
    )


def _numbers(pm: dict[str, list[str]], key: str, path: Path) -> list[float]:
    try:
        return [float(v) for v in pm[key]]
    except KeyError:
        raise InputError(f"{path}: elastix parameter file without {key}") from None
    except ValueError:
        raise InputError(f"{path}: {key} holds a value that is not a number") from None


def _one_transform(pm: dict[str, list[str]], path: Path) -> sitk.Transform:
    """The transform of one elastix parameter file alone (its initial transform left out)."""
    kind = (pm.get("Transform") or [""])[0]
    if kind not in ELASTIX_TRANSFORMS:
        raise InputError(
            f"{path}: elastix {kind or 'unnamed'} transform is not read here (read: "
            f"{', '.join(ELASTIX_TRANSFORMS)})"
        )
    combine = (pm.get("HowToCombineTransforms") or ["Compose"])[0]
    if combine != "Compose":
        raise InputError(f"{path}: HowToCombineTransforms {combine!r} (only 'Compose' is read)")
    if (pm.get("UseDirectionCosines") or ["true"])[0] != "true":
        raise InputError(f"{path}: UseDirectionCosines 'false' is not read (elastix 4.3 style)")
    dim = int(_numbers(pm, "FixedImageDimension", path)[0])
    if dim not in (2, 3):
        raise InputError(f"{path}: FixedImageDimension {dim} (expected 2 or 3)")
    params = _numbers(pm, "TransformParameters", path)
    if kind in ("BSplineTransform", "RecursiveBSplineTransform"):
        try:
            return bspline_from_parameter_map(pm)
        except (KeyError, ValueError, RuntimeError):
            raise InputError(f"{path}: its B-spline grid does not fit its parameters") from None
    if kind == "TranslationTransform":
        t = sitk.TranslationTransform(dim)
    elif kind == "AffineTransform":
        t = sitk.AffineTransform(dim)
    elif kind == "EulerTransform":
        t = sitk.Euler2DTransform() if dim == 2 else sitk.Euler3DTransform()
        if dim == 3:
            t.SetComputeZYX((pm.get("ComputeZYX") or ["false"])[0] == "true")
    else:  # SimilarityTransform
        t = sitk.Similarity2DTransform() if dim == 2 else sitk.Similarity3DTransform()
    if len(params) != t.GetNumberOfParameters():
        raise InputError(
            f"{path}: {len(params)} TransformParameters for a {dim}D {kind} "
            f"(expected {t.GetNumberOfParameters()})"
        )
    if kind != "TranslationTransform":
        center = _numbers(pm, "CenterOfRotationPoint", path)
        if len(center) != dim:
            raise InputError(f"{path}: CenterOfRotationPoint has {len(center)} values, not {dim}")
        t.SetCenter(center)
    t.SetParameters(params)
    return t


def bspline_from_parameter_map(pm: dict[str, list[str]]) -> sitk.BSplineTransform:
    """elastix's B-spline parameter map as a SimpleITK transform (same coefficient layout).

    ITK's BSplineTransform fixed parameters are the coefficient grid's size, origin, spacing
    and direction, which elastix writes as GridSize, GridOrigin, GridSpacing, GridDirection;
    the parameters are the coefficients, all x then all y (then z), in both.

    Raises
    ------
    ValueError
        A grid with a nonzero start index (``GridIndex``), which ITK's fixed parameters
        cannot express.
    KeyError, RuntimeError
        A grid entry is missing, or the parameters do not fit the grid.
    """
    if any(int(v) != 0 for v in pm.get("GridIndex", [])):
        raise ValueError("a B-spline grid with a nonzero start index")
    dim = len(pm["GridSize"])
    order = int(pm.get("BSplineTransformSplineOrder", ["3"])[0])
    t = sitk.BSplineTransform(dim, order)
    fixed = [
        float(v) for k in ("GridSize", "GridOrigin", "GridSpacing", "GridDirection") for v in pm[k]
    ]
    t.SetFixedParameters(fixed)
    t.SetParameters([float(v) for v in pm["TransformParameters"]])
    return t


def final_parameter_file(folder: str | os.PathLike) -> Path | None:
    """The parameter file that stands for the registration an elastix output folder holds.

    Of the folder's ``TransformParameters.<k>.txt``, the one no other names as its initial
    transform (elastix's last run).

    Returns
    -------
    Path or None
        None when the folder holds no ``TransformParameters.<k>.txt``.

    Raises
    ------
    InputError
        Two files or more are each the last of a chain (two registrations in one folder):
        the message names them.
    """
    folder = Path(folder).absolute()
    runs = sorted(
        (p for p in folder.iterdir() if _RUN_FILE.match(p.name)),
        key=lambda p: int(_RUN_FILE.match(p.name)[1]),
    )
    if not runs:
        return None
    initial = set()
    for p in runs:
        nxt = _initial_file(read_parameter_file(p), p)
        if nxt is not None:
            initial.add(nxt.resolve())
    last = [p for p in runs if p.resolve() not in initial]
    if len(last) != 1:
        named = ", ".join(p.name for p in last) if last else "every file"
        raise InputError(
            f"{folder}: two candidate transforms ({named} are each the last of a chain of "
            "elastix runs); keep one registration per folder"
        )
    return last[0]
