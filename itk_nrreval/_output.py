"""Writing results safely: a file appears complete or not at all."""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "atomic_path",
    "write_json",
    "write_text",
    "check_output_folder",
    "staged_folder",
    "json_number",
]


def json_number(value: Any) -> Any:
    """`value` for JSON: a NaN or infinite float becomes None (JSON has neither), a numpy
    float a Python float; anything else passes unchanged."""
    if isinstance(value, (float, np.floating)):
        value = float(value)
        return value if math.isfinite(value) else None
    return value


def check_output_folder(path: str | os.PathLike, *, option: str = "--out") -> Path:
    """Refuse, before any work, an output folder that cannot be one or cannot be written.

    Raises
    ------
    InputError
        `path` is an existing file, or the folder (or its nearest existing parent, where it
        would be created) is not writable.
    """
    from ._errors import InputError

    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(f"{option} {path}: exists and is not a folder")
    existing = path
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise InputError(f"{option} {path}: {existing} is a file, not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise InputError(f"{option} {path}: {existing} is not writable")
    return path


def _default_mode() -> int:
    """Permissions of a newly created file under the current umask (mkstemp uses 0600)."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside `path`; rename it onto `path` only on success.

    The temporary name keeps the final suffix (``.tmp-XXXX.nii.gz``) so that writers that
    choose a format by extension (SimpleITK, matplotlib) still do the right thing.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    suffix = "".join(path.suffixes) or ""
    stem = path.name[: len(path.name) - len(suffix)] if suffix else path.name
    fd, tmp = tempfile.mkstemp(prefix=f".{stem}.tmp-", suffix=suffix, dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.chmod(tmp_path, _default_mode())
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def write_text(path: str | os.PathLike, text: str) -> None:
    """Write `text` to `path` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def write_json(path: str | os.PathLike, data: Any) -> None:
    """Write `data` as indented JSON to `path` atomically."""
    write_text(path, json.dumps(data, indent=2, sort_keys=False) + "\n")


@contextlib.contextmanager
def staged_folder(out: str | os.PathLike, *, keep: tuple[str, ...] = ("cache",)) -> Iterator[Path]:
    """Yield a temporary sibling of `out` to write a whole result into; swap it in on success.

    On success the previous `out` (if any) is replaced by the new folder in two renames,
    carrying over the entries named in `keep` (the per-image cache, which a rerun reuses);
    on failure the temporary folder is removed and `out` is left exactly as it was. So `out`
    always holds one complete result, never a mix of an old run's files and a new one's.
    A process killed mid-run leaves ``<out>.tmp-<pid>-*`` beside `out`, never a damaged `out`.
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_stages(out)
    tmp = Path(tempfile.mkdtemp(prefix=f"{out.name}.tmp-{os.getpid()}-", dir=out.parent))
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    os.chmod(tmp, 0o777 & ~_umask())
    if not out.exists():
        os.rename(tmp, out)
        return
    old = Path(tempfile.mkdtemp(prefix=f"{out.name}.old-{os.getpid()}-", dir=out.parent))
    os.rmdir(old)
    os.rename(out, old)
    os.rename(tmp, out)
    for name in keep:
        if (old / name).exists() and not (out / name).exists():
            os.rename(old / name, out / name)
    shutil.rmtree(old, ignore_errors=True)


def _umask() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return umask


def _remove_stale_stages(out: Path) -> None:
    """Remove ``<out>.tmp-<pid>-*`` / ``<out>.old-<pid>-*`` folders of processes that are gone."""
    stages = [*out.parent.glob(f"{out.name}.tmp-*-*"), *out.parent.glob(f"{out.name}.old-*-*")]
    for path in stages:
        pid = path.name[len(out.name) + 5 :].split("-", 1)[0]
        if not pid.isdigit() or not path.is_dir():
            continue
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            shutil.rmtree(path, ignore_errors=True)
        except PermissionError:
            pass
