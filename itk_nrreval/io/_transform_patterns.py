"""Registrations' outputs found by shell pattern, by subject: what the wildcards of a pattern
(``"out/sub-*_"``) match is the subject's label. ANTs prefixes give each subject's chain in
``fwdtransforms`` order, elastix output folders their last parameter file, FSL and NiftyReg
files an entry naming their format.

What :func:`itk_nrreval.io.pipeline_outputs.manifest_from_transforms` reads its registrations with.
"""

from __future__ import annotations

import glob
import os
import re
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path

from .._errors import InputError
from ._elastix_files import final_parameter_file, read_parameter_file
from ._foreign_transforms import method_of_file

__all__ = ["engines_of", "matches", "method_written", "registrations_found", "subject_label"]


def _pattern_regex(pattern: str) -> str:
    """A shell pattern as a regular expression whose groups are what its wildcards match."""
    out, i = [], 0
    while i < len(pattern):
        c = pattern[i]
        if c == "*":
            while i + 1 < len(pattern) and pattern[i + 1] == "*":
                i += 1
            out.append("([^/]*)")
        elif c == "?":
            out.append("([^/])")
        elif c == "[" and "]" in pattern[i + 2 :]:
            end = pattern.index("]", i + 2)
            body = pattern[i + 1 : end]
            body = "^" + body[1:] if body.startswith("!") else body
            out.append(f"([{body.replace(chr(92), chr(92) * 2)}])")
            i = end
        else:
            out.append(re.escape(c))
        i += 1
    return "".join(out)


def matches(pattern: str, tail: str = "", *, what: str) -> dict[tuple, list[tuple[Path, tuple]]]:
    """Files (or folders) matching `pattern` then the regular expression `tail`, by subject
    label (what the wildcards matched): label -> [(path, tail's groups)]."""
    pattern = os.path.expanduser(pattern)
    if not any(c in pattern for c in "*?["):
        raise InputError(
            f"{what} {pattern}: no * in the pattern to stand for the subject (quote the "
            "pattern: the shell replaces an unquoted one by the files it matches)"
        )
    regex = re.compile(_pattern_regex(pattern.rstrip("/")) + tail + "/?$")
    n_wild = re.compile(_pattern_regex(pattern.rstrip("/"))).groups
    out: dict[tuple, list] = {}
    for name in sorted(glob.glob(pattern + ("*" if tail else ""))):
        m = regex.match(name)
        if m is None:
            continue
        groups = m.groups()
        out.setdefault(groups[:n_wild], []).append((Path(name).absolute(), groups[n_wild:]))
    return out


def subject_label(key: tuple) -> str:
    return "/".join(key)


_ANTS_TAIL = (
    r"(?:(\d+)(GenericAffine|Rigid|Affine|Similarity|Translation)\.mat|(\d+)(Warp)\.nii(?:\.gz)?"
    r"|(Composite)\.h5)"
)


def _ants_chains(pattern: str, *, what: str) -> dict[tuple, list[Path]]:
    """Subject -> its ANTs chain in ``fwdtransforms`` order (highest stage first)."""
    chains = {}
    for key, files in matches(pattern, _ANTS_TAIL, what=what).items():
        composite = [p for p, g in files if g[4]]
        stages = sorted(((int(g[0] or g[2]), p) for p, g in files if not g[4]), key=lambda s: -s[0])
        if composite and stages:
            raise InputError(
                f"{composite[0]}: two candidate transforms for subject {subject_label(key)} "
                f"(this and {stages[0][1].name}); keep one"
            )
        numbers = [k for k, _ in stages]
        if len(set(numbers)) != len(numbers):
            dup = next(p for k, p in stages if numbers.count(k) > 1)
            raise InputError(
                f"{dup}: two candidate transforms for subject {subject_label(key)} at one ANTs "
                "stage"
            )
        chains[key] = composite or [p for _, p in stages]
    return chains


def _elastix_files(pattern: str, *, what: str) -> dict[tuple, list[Path]]:
    """Subject -> [its elastix output folder's last parameter file]."""
    out = {}
    for key, found in matches(pattern, what=what).items():
        folder = found[0][0]
        if not folder.is_dir():
            continue
        last = final_parameter_file(folder)
        if last is None:
            # a warning of manifest_from_transforms' caller (through registrations_found)
            warnings.warn(f"{folder}: no TransformParameters.<k>.txt; left out", stacklevel=4)
            continue
        out[key] = [last]
    return out


def _foreign_files(fmt: str):
    """The reader of a pattern of transform files in another tool's format (``fsl``,
    ``niftyreg``): subject -> [its manifest entry, ``{file:, format:}``], whose images default
    to the reference and the subject's image (:mod:`itk_nrreval.io._foreign_transforms`)."""

    def read(pattern: str, *, what: str) -> dict[tuple, list]:
        out = {}
        for key, found in matches(pattern, what=what).items():
            files = [p for p, _ in found if p.is_file()]
            if len(files) > 1:
                raise InputError(
                    f"{files[1]}: two candidate transforms for subject {subject_label(key)} "
                    f"(this and {files[0].name}); make the pattern match one"
                )
            if files:
                out[key] = [{"file": str(files[0]), "format": fmt}]
        return out

    return read


def _file_of(item) -> str:
    """The file of a chain item: a path, or an entry naming its format."""
    return str(item["file"]) if isinstance(item, Mapping) else str(item)


def _named(value: Mapping[str, str] | Sequence[str] | str | None, default: str) -> dict:
    """Registrations given as {name: pattern}, [pattern, ...], or one pattern."""
    if value is None:
        return {}
    if isinstance(value, Mapping):
        return dict(value)
    items = [value] if isinstance(value, str) else list(value)
    return {default if k == 0 else f"{default}-{k + 1}": p for k, p in enumerate(items)}


def registrations_found(
    image_of: dict[tuple, Path],
    *,
    ants: Mapping[str, str] | Sequence[str] | str | None,
    elastix: Mapping[str, str] | Sequence[str] | str | None,
    fsl: Mapping[str, str] | Sequence[str] | str | None,
    niftyreg: Mapping[str, str] | Sequence[str] | str | None,
) -> dict[str, dict[tuple, list[Path]]]:
    """Per registration of :func:`~itk_nrreval.io.pipeline_outputs.manifest_from_transforms` (ANTs,
    elastix, FSL, NiftyReg, in that order), each subject's chain, every transform matched to
    its image in `image_of`.

    Raises
    ------
    InputError
        No registration given, two of one name, a pattern matching no transform, or a
        transform without its image.
    """
    registrations: dict[str, dict[tuple, list[Path]]] = {}
    named = [
        *((n, p, _ants_chains, "--ants") for n, p in _named(ants, "ants").items()),
        *((n, p, _elastix_files, "--elastix") for n, p in _named(elastix, "elastix").items()),
        *((n, p, _foreign_files("fsl"), "--fsl") for n, p in _named(fsl, "fsl").items()),
        *(
            (n, p, _foreign_files("niftyreg"), "--niftyreg")
            for n, p in _named(niftyreg, "niftyreg").items()
        ),
    ]
    if not named:
        raise InputError("no registration given (--ants, --elastix, --fsl or --niftyreg)")
    for name, pattern, read, option in named:
        if name in registrations:
            raise InputError(f"{option} {pattern}: a second registration named {name!r}")
        chains = read(pattern, what=option)
        if not chains:
            raise InputError(f"{option} {pattern}: no transform matches")
        for key, chain in chains.items():
            if key not in image_of:
                raise InputError(
                    f"{_file_of(chain[0])}: a transform without its image (no --images file "
                    f"for subject {subject_label(key)})"
                )
        registrations[name] = chains
    return registrations


def engines_of(
    *,
    ants: Mapping[str, str] | Sequence[str] | str | None,
    elastix: Mapping[str, str] | Sequence[str] | str | None,
    fsl: Mapping[str, str] | Sequence[str] | str | None,
    niftyreg: Mapping[str, str] | Sequence[str] | str | None,
) -> dict[str, str]:
    """Registration name -> the tool whose files it reads (``ants``, ``elastix``, ``fsl``,
    ``niftyreg``), named as :func:`registrations_found` names them."""
    given = {"ants": ants, "elastix": elastix, "fsl": fsl, "niftyreg": niftyreg}
    return {name: engine for engine, value in given.items() for name in _named(value, engine)}


def method_written(engine: str, chains: Mapping[tuple, list]) -> str | None:
    """The method a registration's files name, where every subject's files name the same one;
    else None (the files do not say, or subjects differ).

    What each tool's files say: an ANTs chain without a warp (``*GenericAffine.mat`` and the
    like) is ``affine``; a warp or a ``Composite.h5`` does not say which of SyN, B-spline SyN
    or another wrote it. An elastix folder's last parameter file names its ``Transform``
    (``BSplineTransform``, ``AffineTransform``...). An FSL matrix is ``flirt``, an FNIRT
    coefficient file ``fnirt``; an FSL displacement field does not say (convertwarp writes
    them too). A NiftyReg matrix is ``aladin``; a field converted by ``reg_transform`` does not
    say which registration made it.

    With ``engine``, the method is the registration's family (``parameters: method, engine``),
    which the verdict reads: it weighs roughness against specificity only between settings
    of one method (:mod:`itk_nrreval.measures.verdict`).
    """
    methods = {_method_of(engine, chain) for chain in chains.values()}
    return methods.pop() if len(methods) == 1 else None


def _method_of(engine: str, chain: list) -> str | None:
    """The method one subject's chain names (:func:`method_written`), or None."""
    if engine == "ants":
        names = [Path(p).name for p in chain]
        linear = all(n.endswith(".mat") for n in names)
        return "affine" if linear else None
    if engine == "elastix":
        transform = read_parameter_file(chain[-1]).get("Transform") or [None]
        return transform[0]
    return method_of_file(_file_of(chain[-1]), engine)
