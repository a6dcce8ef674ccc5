"""Label names: what each integer value of a label map stands for.

Read from a BIDS ``dseg.tsv`` (tab-separated, a header with columns ``index`` and ``name``,
optionally more), a FreeSurfer ``FreeSurferColorLUT.txt``-style table (lines
``value name R G B A``, ``#`` comments), or given as a mapping value -> name (a manifest's
``label_names``). The names are shown beside the values in the per-label tables, the
per-label entries of ``results.json``, ``metrics.csv`` and the report; without names, the
values alone, as before.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

from .._errors import InputError

__all__ = ["read_label_names", "label_names_from", "label_text"]


def read_label_names(path: str | os.PathLike) -> dict[int, str]:
    """Read a BIDS ``dseg.tsv`` or a FreeSurfer colour lookup table.

    Parameters
    ----------
    path : path
        A tab-separated table whose first line is a header with ``index`` and ``name``
        columns (BIDS), or a FreeSurfer-style table of ``value name R G B A`` lines with
        ``#`` comments and blank lines.

    Returns
    -------
    dict of int to str
        Label value -> name, in the file's order.

    Raises
    ------
    InputError
        One line naming the file: not found or unreadable, missing columns, a
        non-integer index, a duplicate index or no names at all.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise InputError(f"{p}: label names file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{p}: cannot read the label names ({exc})") from None
    lines = [(i + 1, line) for i, line in enumerate(text.splitlines())]
    first = next((line for _, line in lines if line.strip()), "")
    header = [c.strip().lower() for c in first.split("\t")]
    if "\t" in first or "index" in header or "name" in header:
        return _bids(p, lines)
    return _freesurfer(p, lines)


def _bids(p: Path, lines: list[tuple[int, str]]) -> dict[int, str]:
    rows = [(n, line) for n, line in lines if line.strip()]
    header = [c.strip().lower() for c in rows[0][1].split("\t")]
    missing = [c for c in ("index", "name") if c not in header]
    if missing:
        raise InputError(
            f"{p}: a dseg.tsv needs the columns 'index' and 'name' (missing "
            f"{', '.join(repr(c) for c in missing)})"
        )
    i_index, i_name = header.index("index"), header.index("name")
    pairs = []
    for n, line in rows[1:]:
        cells = line.split("\t")
        if len(cells) <= max(i_index, i_name):
            raise InputError(f"{p}: line {n}: expected {len(header)} tab-separated columns")
        pairs.append((n, cells[i_index].strip(), cells[i_name].strip()))
    return _checked(p, pairs)


def _freesurfer(p: Path, lines: list[tuple[int, str]]) -> dict[int, str]:
    pairs = []
    for n, line in lines:
        content = line.split("#", 1)[0].strip()
        if not content:
            continue
        cells = content.split()
        if len(cells) < 2:
            raise InputError(f"{p}: line {n}: expected 'value name R G B A', got {content!r}")
        pairs.append((n, cells[0], cells[1]))
    return _checked(p, pairs)


def _checked(p: Path, pairs: list[tuple[int, str, str]]) -> dict[int, str]:
    out: dict[int, str] = {}
    for n, index, name in pairs:
        try:
            value = int(index)
        except ValueError:
            raise InputError(f"{p}: line {n}: index {index!r} is not an integer") from None
        if value in out:
            raise InputError(f"{p}: line {n}: duplicate index {value}")
        if not name:
            raise InputError(f"{p}: line {n}: label {value} has no name")
        out[value] = name
    if not out:
        raise InputError(f"{p}: no label names")
    return out


def label_names_from(value, base: str | os.PathLike | None = None) -> dict[int, str]:
    """Label names from a manifest's ``label_names``: a file path or a mapping.

    Parameters
    ----------
    value : path or mapping
        A path to a ``dseg.tsv`` or FreeSurfer lookup table (relative to `base`), or a
        mapping label value (int, or a string of one) -> name.
    base : path, optional
        Folder a relative path is relative to (default: the current directory).

    Returns
    -------
    dict of int to str

    Raises
    ------
    InputError
        A file as in :func:`read_label_names`, a mapping key that is not an integer, an
        empty name, or any other kind of value.
    """
    if isinstance(value, Mapping):
        out: dict[int, str] = {}
        for k, v in value.items():
            try:
                key = int(k) if not isinstance(k, bool) else None
            except (TypeError, ValueError):
                key = None
            if key is None or (isinstance(k, float) and k != key):
                raise InputError(f"label_names: key {k!r} is not an integer label value")
            if key in out:
                raise InputError(f"label_names: duplicate label value {key}")
            if not isinstance(v, (str, int)) or not str(v).strip():
                raise InputError(f"label_names: label {key} has no name (got {v!r})")
            out[key] = str(v).strip()
        return out
    if isinstance(value, (str, os.PathLike)) and str(value).strip():
        p = Path(os.path.expanduser(str(value)))
        if not p.is_absolute():
            p = Path(base if base is not None else ".") / p
        return read_label_names(Path(os.path.normpath(p)))
    raise InputError(
        f"label_names: expected a dseg.tsv or lookup-table path, or a mapping value -> name, "
        f"got {type(value).__name__}"
    )


def label_text(value: int, names: Mapping[int, str] | None) -> str:
    """``"3 (hippocampus)"`` where `value` has a name, else ``"3"``."""
    name = None if names is None else names.get(int(value))
    return str(value) if name is None else f"{value} ({name})"
