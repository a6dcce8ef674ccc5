"""Writing results safely: a file appears complete or not at all."""

from __future__ import annotations

import contextlib
import fcntl
import json
import math
import os
import shutil
import signal
import sys
import tempfile
import threading
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "atomic_path",
    "write_json",
    "write_text",
    "check_output_folder",
    "check_output_file",
    "json_written_by_nrreval",
    "staged_folder",
    "claim_output_folder",
    "claim_entries",
    "json_number",
]


def json_number(value: Any) -> Any:
    """`value` for JSON: a NaN or infinite float becomes None (JSON has neither), a numpy
    float a Python float; anything else passes unchanged."""
    if isinstance(value, (float, np.floating)):
        value = float(value)
        return value if math.isfinite(value) else None
    return value


MARKER = ".nrreval-output.json"
"""The record, inside every output folder the toolkit makes, of the command that made it
and the entries it wrote there: the only entries a later run of the same command may
replace."""


def _refuse_other_command(
    folder: Path, given: str | os.PathLike, option: str, command: str
) -> None:
    """Refuse `folder` when its record says another command made it (or does not say which).

    A rerun replaces what the same command wrote; another command's output -- a synth
    folder's images, a register folder's transforms, hours of 3D work -- is never replaced.
    """
    from ._errors import InputError

    if _read_record(folder) is None:
        return
    made_by = _record_command(folder)
    if made_by == command:
        return
    who = (
        f"`nrreval {made_by}`"
        if made_by
        else "an earlier nrreval version that did not record which command wrote it"
    )
    raise InputError(
        f"{option} {given}: holds the output of {who}; `nrreval {command}` may replace only "
        "its own output: choose another folder (nothing was written)"
    )


def check_output_folder(
    path: str | os.PathLike,
    *,
    inputs: Iterable[str | os.PathLike] = (),
    option: str = "--out",
    shared: bool = False,
    command: str | None = None,
) -> Path:
    """Refuse, before any work, an output folder that cannot be one or could cost a file.

    A folder is accepted when it does not exist yet, is empty, or was made by the same
    command of this toolkit (it holds :data:`MARKER` naming `command`; a rerun into it
    resumes). Writing into it later (:func:`staged_folder`) replaces only the entries the
    record names. A folder another command made (a ``synth`` folder given to ``evaluate``)
    is refused: its files are that command's work, not this one's to replace.

    Parameters
    ----------
    path : path
        The output folder.
    inputs : paths, keyword-only
        Every file the command reads. The output folder may not be one of them, nor hold one
        at any depth (a folder swapped in over its inputs would lose them).
    option : str, keyword-only
        The option's name, for the message.
    shared : bool, keyword-only
        Accept any folder that holds no input: for a folder whose writer touches only
        entries of its own naming (the per-image cache), which may hold other things.
    command : str, keyword-only
        The command that will write there (``"evaluate"``, ``"synth"``, ...); required
        unless `shared`.

    Returns
    -------
    Path
        `path`, absolute and with symbolic links resolved (``--out .`` names the folder,
        not the working directory's alias of it).

    Raises
    ------
    InputError
        `path` is an existing file, holds or is an input, is a non-empty folder this toolkit
        did not make or another command made, or is not writable (nor is its nearest
        existing parent).
    """
    from ._errors import InputError

    if command is None and not shared:
        raise TypeError("check_output_folder: command= is required for an output folder")
    given = Path(path)
    path = given.resolve()
    if path.exists() and not path.is_dir():
        raise InputError(f"{option} {given}: exists and is not a folder")
    for item in inputs:
        item = Path(item).resolve()
        if item == path or path in item.parents:
            raise InputError(
                f"{option} {given}: holds the input {item}; "
                "choose a folder outside the inputs (nothing was written)"
            )
    existing = path
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise InputError(f"{option} {given}: {existing} is a file, not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise InputError(f"{option} {given}: {existing} is not writable")
    if not shared and existing == path and _read_record(path) is None and any(path.iterdir()):
        raise InputError(
            f"{option} {given}: a folder that nrreval did not make, and not empty; "
            "choose a new or empty folder (nothing was written)"
        )
    if not shared and existing == path:
        _refuse_other_command(path, given, option, command)
    return path


def check_output_file(
    path: str | os.PathLike,
    *,
    inputs: Iterable[str | os.PathLike] = (),
    option: str,
    ours: Callable[[Path], bool],
) -> Path:
    """Refuse, before any work, an output file that cannot be one or is someone else's.

    Parameters
    ----------
    path : path
        The file to write.
    inputs : paths, keyword-only
        Every file the command reads: `path` may not be one of them.
    option : str, keyword-only
        The option's name, for the message.
    ours : callable, keyword-only
        Whether an existing file at `path` is one this toolkit wrote (and so may replace).

    Returns
    -------
    Path

    Raises
    ------
    InputError
        `path` is a folder, an input, an existing file the toolkit did not write, or cannot
        be created.
    """
    from ._errors import InputError

    given = Path(path)
    path = given.resolve()
    if path.is_dir():
        raise InputError(f"{option} {given}: is a folder; give a file name")
    if any(Path(item).resolve() == path for item in inputs):
        raise InputError(f"{option} {given}: is one of the inputs")
    if path.exists() and not ours(path):
        raise InputError(
            f"{option} {given}: exists and was not written by nrreval; "
            "choose another name (nothing was written)"
        )
    check_output_folder(path.parent, option=f"{option} {given}: its folder", shared=True)
    return path


def json_written_by_nrreval(path: Path) -> bool:
    """Whether `path` is a JSON object whose ``"tool"`` is :data:`TOOL`, as the toolkit's
    single-file JSON records are (an `ours` of :func:`check_output_file`)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        return False
    return isinstance(data, dict) and data.get("tool") == TOOL


TOOL = "itk-nrreval"
"""What the toolkit's own records name as their writer."""


def _read_record(folder: Path) -> set[str] | None:
    """The entries :data:`MARKER` says the toolkit wrote into `folder`, or None where there
    is no (readable) record: a folder the toolkit did not make."""
    try:
        data = json.loads((folder / MARKER).read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    if not isinstance(data, dict) or data.get("tool") != TOOL:
        return None
    entries = data.get("entries", [])
    if not isinstance(entries, list) or not all(isinstance(e, str) for e in entries):
        return None
    return {e for e in entries if e and "/" not in e and e not in (".", "..", MARKER)}


def _record_command(folder: Path) -> str | None:
    """The command the record of `folder` names as its writer (None: not named, as in the
    records of versions before it was kept)."""
    try:
        data = json.loads((folder / MARKER).read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    command = data.get("command") if isinstance(data, dict) else None
    return command if isinstance(command, str) else None


def _write_record(folder: Path, entries: Iterable[str], *, command: str | None) -> None:
    from ._version import __version__

    record = {"tool": TOOL, "version": __version__, "command": command}
    write_json(folder / MARKER, {**record, "entries": sorted(entries)})


_HELD_LOCKS: dict[Path, int] = {}
"""Folders this process holds locked for its lifetime (:func:`claim_output_folder`), by
path: a second claim in the same process does not lock itself out."""


def _lock_folder(folder: Path) -> int | None:
    """Lock `folder` against other nrreval processes writing into it; the lock's descriptor
    (close it to release), or None where this process already holds it.

    An advisory ``flock`` on the folder itself: no lock file to leave behind, and a process
    that dies releases it with its descriptors.

    Raises
    ------
    InputError
        Another process holds the lock (two runs into one ``--out`` would each replace the
        other's entries and remove cache entries the other is reading).
    """
    from ._errors import InputError

    if folder in _HELD_LOCKS:
        return None
    fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise InputError(
            f"{folder}: another nrreval run is writing into this folder; wait for it to end, "
            "or choose another folder (nothing was written)"
        ) from None
    return fd


def _unlock(fd: int | None) -> None:
    if fd is not None:
        os.close(fd)


_swaps_done = 0
"""How many :func:`staged_folder` results this process has put in place: the command line
drops a Ctrl-C that arrives after its command's result is complete (see
:func:`swaps_done`)."""


def swaps_done() -> int:
    """How many staged results (:func:`staged_folder`) this process has swapped in so far.

    The command line reads it before a command runs and in its SIGINT handler: once the
    count has grown, the command's result is complete, and an interrupt then must not end
    the command with exit code 130, which says that the previous result was kept.
    """
    return _swaps_done


@contextlib.contextmanager
def sigint_handled_by(handler) -> Iterator[None]:
    """Handle Ctrl-C (SIGINT) with `handler` for the block, then as before it.

    Only the main thread can set signal handlers; elsewhere (a Slicer or Dask thread) the
    block runs with the handler there is. Meanwhile a KeyboardInterrupt raised where it
    cannot propagate is sent again (:func:`_interrupts_delivered_again`), not printed.
    """
    try:
        previous = signal.signal(signal.SIGINT, handler)
    except ValueError:  # not the main thread
        yield
        return
    previous_hook, active = sys.unraisablehook, threading.Event()
    active.set()
    sys.unraisablehook = _interrupts_delivered_again(previous_hook, active)
    try:
        yield
    finally:
        active.clear()
        sys.unraisablehook = previous_hook
        signal.signal(signal.SIGINT, previous)


def _interrupts_delivered_again(previous_hook, active: threading.Event):
    """A ``sys.unraisablehook`` that sends Ctrl-C again when its KeyboardInterrupt was raised
    where it cannot propagate, and passes anything else to `previous_hook`.

    Ctrl-C that lands in a callback from compiled code (llvmlite's ctypes callbacks while
    numba loads its cache) or in a ``__del__`` is reported as "Exception ignored" with a
    traceback, and the command carries on. Sent again from another thread, 50 ms later (a
    signal sent in the hook itself would be handled in the hook, and be unraisable again),
    the main thread's handler takes it at its next bytecode, outside that callback; `active`
    is cleared when the handler is no longer the command's.
    """

    def send_again() -> None:
        if active.is_set():
            os.kill(os.getpid(), signal.SIGINT)

    def hook(unraisable) -> None:
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            # a little later: Thread.start waits for the thread, and a signal sent at once
            # would be handled here, in the hook
            timer = threading.Timer(0.05, send_again)
            timer.daemon = True
            timer.start()
            return
        previous_hook(unraisable)

    return hook


def _interrupts_held_off():
    """Hold off Ctrl-C (SIGINT) for a few renames that must happen all or not at all.

    An interrupt that arrives meanwhile is dropped: once the renames are done the result is
    complete, and an exit code 130 would say that the previous result was kept when it was
    replaced (the command line drops it after the swap too: :func:`swaps_done`).
    """
    return sigint_handled_by(lambda signum, frame: None)


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


def claim_output_folder(out: str | os.PathLike, *, entries: Iterable[str], command: str) -> Path:
    """Make `out` this toolkit's folder for a run of `command` that writes `entries` in place.

    For the commands whose results are written where they stay (``demo``, ``sweep``: a
    rerun reuses their registrations), rather than staged (:func:`staged_folder`). `out`
    should have passed :func:`check_output_folder`.

    Parameters
    ----------
    out : path
        The output folder: created where missing.
    entries : str, keyword-only
        The top-level names the run writes (files or folders).
    command : str, keyword-only
        The command writing there: a folder another command made is refused.

    Returns
    -------
    Path
        `out`, absolute. It stays locked against other nrreval processes until this one
        ends.

    Raises
    ------
    InputError
        `out` is a non-empty folder the toolkit did not make or another command made, one of
        `entries` exists there and was not written by the toolkit, or another nrreval
        process is writing there.
    """
    from ._errors import InputError

    out = Path(out).resolve()
    previous, _, lock = _claim(out, command=command)
    try:
        previous = previous or set()
        entries = set(entries)
        foreign = sorted(n for n in entries - previous if os.path.lexists(out / n))
        if foreign:
            raise InputError(
                f"{out / foreign[0]}: was not written by nrreval and would be replaced"
            )
        _write_record(out, previous | entries, command=command)
    except BaseException:
        _unlock(lock)
        raise
    if lock is not None:
        _HELD_LOCKS[out] = lock
    return out


def claim_entries(folder: str | os.PathLike, names: Iterable[str], *, command: str) -> Path:
    """Before a result's ``write`` into `folder`: refuse, before anything is written, to
    replace an entry the toolkit did not write; then record `names` as the toolkit's.

    The Python API's writers (``register(out=)``, each result's ``write``) may write into a
    user's own folder, beside the user's files; this keeps them from replacing one that
    happens to share a name (``report.html``, ``reference.nii.gz``). An entry is the
    toolkit's when the folder's record (:data:`MARKER`) names it, or when the folder itself
    lies inside an entry of the toolkit's (a demo's ``registrations/fluid``, a staged
    result).

    Parameters
    ----------
    folder : path
        Created where missing.
    names : str
        The top-level names about to be written there.
    command : str, keyword-only
        The command (or the API's counterpart of one) writing them: a folder whose record
        names another command is refused.

    Returns
    -------
    Path
        `folder`, absolute.

    Raises
    ------
    InputError
        `folder` is a file, another command's output folder, or one of `names` exists
        there and was not written by the toolkit (nothing is written).
    """
    from ._errors import InputError

    folder = Path(folder).resolve()
    if folder.exists() and not folder.is_dir():
        raise InputError(f"{folder}: exists and is not a folder")
    names = set(names)
    if _inside_an_entry_of_ours(folder):
        folder.mkdir(parents=True, exist_ok=True)
        return folder
    _refuse_other_command(folder, folder, "the output folder", command)
    record = _read_record(folder) or set()
    foreign = sorted(n for n in names - record if os.path.lexists(folder / n))
    if foreign:
        raise InputError(
            f"{folder / foreign[0]}: exists and was not written by nrreval; "
            "write into a new folder, or move the file (nothing was written)"
        )
    folder.mkdir(parents=True, exist_ok=True)
    _write_record(folder, record | names, command=command)
    return folder


def _inside_an_entry_of_ours(folder: Path) -> bool:
    """Whether `folder` lies inside an entry the toolkit recorded in a folder above it, or
    is one of :func:`staged_folder`'s temporary folders."""
    for parent, child in zip(folder.parents, [folder, *folder.parents], strict=False):
        record = _read_record(parent)
        if record is not None and (child.name in record or child.name.startswith(_STAGE)):
            return True
    return False


@contextlib.contextmanager
def staged_folder(
    out: str | os.PathLike, *, command: str, keep: tuple[str, ...] = ("cache",)
) -> Iterator[Path]:
    """Yield a temporary folder to write a whole result into; move it into `out` on success.

    `out` is claimed on entry: created where missing, and marked as this toolkit's
    (:data:`MARKER`, the record of the entries it wrote). Entries named in `keep` (the
    per-image cache, which a rerun reuses) are written straight into `out` while the work
    runs. On success, the previous run's recorded entries are moved aside, the new ones moved
    in, the record rewritten and the old entries removed: entries the toolkit did not write
    (a user's notes) are never moved, replaced or deleted. On bad input
    (:class:`InputError`), `out` is put back as it was: what this run added to the `keep`
    entries, and `out` itself if this run made it, are removed. An interrupted run keeps them
    (a rerun resumes). The temporary folder is a hidden entry of `out`; a process killed
    mid-run leaves it there, and the next run removes it. `out` is locked against other
    nrreval processes while the run lasts, and the final swap is not cut short by Ctrl-C
    (an interrupt during it is dropped: the new result is then complete).

    Raises
    ------
    InputError
        `out` is a non-empty folder the toolkit did not make or another command made,
        another nrreval process is writing there, or a new entry would replace a file the
        toolkit did not write (the new result is then left in the temporary folder, whose
        name the message gives).
    """
    from ._errors import InputError

    global _swaps_done
    out = Path(out).resolve()
    previous, made, lock = _claim(out, command=command)
    try:
        before = {k: _names_below(out / k) for k in keep}
        new_keeps = {k for k, names in before.items() if names is None}
        _write_record(out, (previous or set()) | new_keeps, command=command)
        _remove_stale_stages(out)
        tmp = Path(tempfile.mkdtemp(prefix=f"{_STAGE}tmp-{os.getpid()}-", dir=out))
        try:
            yield tmp
        except InputError:
            shutil.rmtree(tmp, ignore_errors=True)
            _restore(out, before, previous=previous, made=made, command=command)
            raise
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        staged = sorted(os.listdir(tmp))
        record = _read_record(out) or set()
        foreign = [n for n in staged if os.path.lexists(out / n) and n not in record]
        if foreign:
            raise InputError(
                f"{out / foreign[0]}: was not written by nrreval and would be replaced; "
                f"the new results are in {tmp}"
            )
        with _interrupts_held_off():  # the swap: all of it, never half a result
            old = Path(tempfile.mkdtemp(prefix=f"{_STAGE}old-{os.getpid()}-", dir=out))
            for name in sorted(record):
                if os.path.lexists(out / name) and (name in staged or name not in keep):
                    os.rename(out / name, old / name)
            for name in staged:
                os.rename(tmp / name, out / name)
            kept = [k for k in keep if (out / k).exists()]
            _write_record(out, [*staged, *kept], command=command)
            os.rmdir(tmp)
            _swaps_done += 1
        shutil.rmtree(old, ignore_errors=True)
    finally:
        _unlock(lock)


def _claim(out: Path, *, command: str) -> tuple[set[str] | None, bool, int | None]:
    """Create `out` where missing and lock it; its record (None: the toolkit has not written
    there), whether this call made it, and the lock (:func:`_lock_folder`). Refuses a
    non-empty folder the toolkit did not make, one another command made, and one another
    process is writing into."""
    from ._errors import InputError

    made = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    lock = _lock_folder(out)
    try:
        previous = _read_record(out)
        if previous is None and any(out.iterdir()):
            raise InputError(f"{out}: a folder that nrreval did not make, and not empty")
        _refuse_other_command(out, out, "the output folder", command)
    except BaseException:
        _unlock(lock)
        if made:
            with contextlib.suppress(OSError):
                out.rmdir()
        raise
    return previous, made, lock


def _names_below(path: Path) -> set[str] | None:
    """Every path below `path`, relative to it (None where `path` does not exist)."""
    if not path.exists():
        return None
    return {str(p.relative_to(path)) for p in path.rglob("*")}


def _restore(
    out: Path,
    before: dict[str, set[str] | None],
    *,
    previous: set[str] | None,
    made: bool,
    command: str,
) -> None:
    """Undo what a failed run added to `out`: to its `keep` entries, its record (`previous`,
    None where `out` had none), and `out` itself where the run made it."""
    for name, names in before.items():
        path = out / name
        if names is None:
            shutil.rmtree(path, ignore_errors=True)
        elif path.is_dir():
            added = [p for p in path.rglob("*") if str(p.relative_to(path)) not in names]
            for p in sorted(added, key=lambda p: len(p.parts)):
                if p.is_dir():
                    shutil.rmtree(p, ignore_errors=True)
                elif os.path.lexists(p):
                    p.unlink()
    if previous is not None:
        _write_record(out, previous, command=command)
        return
    (out / MARKER).unlink(missing_ok=True)
    if made:
        with contextlib.suppress(OSError):  # not empty: a file someone else put there
            out.rmdir()


_STAGE = ".nrreval-stage-"


def _remove_stale_stages(out: Path) -> None:
    """Remove the ``.nrreval-stage-{tmp,old}-<pid>-*`` folders in `out` of processes that
    are gone (a run killed mid-write)."""
    for path in out.glob(f"{_STAGE}*-*-*"):
        pid = path.name[len(_STAGE) :].split("-")[1]
        if not pid.isdigit() or not path.is_dir():
            continue
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            shutil.rmtree(path, ignore_errors=True)
        except PermissionError:
            pass
