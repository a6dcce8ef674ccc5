"""A content-addressed disk cache for per-image results, safe to share between processes.

An entry is a folder ``<root>/<kind>/<key>/`` holding numpy arrays (``.npy``) and a
``entry.json`` that lists every array file's CRC-32 and byte size, plus small JSON
metadata. The key is a digest of everything the result depends on (input images and
transforms, settings; :func:`digest_of`), so a changed input gives a new key and an
unchanged one finds its entry again, on any machine that sees the folder, in any process.

Inputs are keyed by what they hold, never by object identity or file name: an image by its
pixel type, grid and voxel values, a transform by its pieces' types and parameters (a
displacement field by its values and grid) -- whether it is a file (decoded,
:func:`content_digest`) or an object in memory (``sitk.Image``, ``sitk.Transform``, a
manifest's in-memory item). A file and the same image or transform in memory therefore share
their cache entries.

Writes go to a private temporary folder that is renamed into place only when complete,
so a process killed mid-write leaves no entry, only a ``*.tmp-<host>-<pid>-*`` folder that
is ignored and removed by the next run on that host (:meth:`DiskCache.remove_stale`). Reads
check every array file's size and CRC-32 (against damage, not tampering: it misses a
random change once in 4e9 and a burst of up to 32 bits never, at twice the speed of a
cryptographic digest): an entry that fails (truncated, bit-flipped, missing file,
unreadable JSON) is reported as absent and removed, so the caller recomputes it -- a
corrupt entry is never trusted.

Several runs may share one cache (a cluster's ``--cache``). A run marks the cache as in use
(:meth:`DiskCache.in_use`) while it lasts; an entry it no longer needs is removed only while
no other run uses the cache, so an entry another run has found is never pulled from under
it. Removals held off that way are tried again when the run ends.
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
import hashlib
import json
import os
import shutil
import socket
import uuid
import zlib
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .._executors import NPY_HEADER_LOCK

__all__ = ["DiskCache", "CacheEntry", "digest_of", "file_digest", "content_digest"]

_FORMAT = 2  # 2: CRC-32 of each array file (1: BLAKE2b)
_BLOCK = 1 << 20


def file_digest(path: str | os.PathLike) -> str:
    """BLAKE2b (128-bit) hex digest of a file's bytes."""
    h = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as f:
        while chunk := f.read(_BLOCK):
            h.update(chunk)
    return h.hexdigest()


def _file_crc32(path: Path) -> str:
    """CRC-32 of a file's bytes, as stored in an entry (``"crc32:<8 hex digits>"``)."""
    crc = 0
    with open(path, "rb") as f:
        while chunk := f.read(_BLOCK):
            crc = zlib.crc32(chunk, crc)
    return f"crc32:{crc:08x}"


def _save_array(path: Path, arr: np.ndarray) -> str:
    """Write `arr` as ``.npy`` at `path`; return the file's :func:`_file_crc32`, taken from
    the header read back and the array in memory (not the whole file read back)."""
    if not arr.flags.c_contiguous:  # (np.ascontiguousarray would make a 0-d array 1-d)
        arr = arr.copy(order="C")
    with open(path, "wb") as f:
        np.lib.format.write_array(f, arr, allow_pickle=False)
        size = f.tell()
    with open(path, "rb") as f:
        crc = zlib.crc32(f.read(size - arr.nbytes))
    crc = zlib.crc32(arr.reshape(-1).view(np.uint8), crc)
    return f"crc32:{crc:08x}"


def content_digest(path: str | os.PathLike) -> str:
    """Digest of what a file holds once decoded: the key of a file in :func:`digest_of`.

    A transform file (``.tfm``, ``.txt``, ``.h5``, ``.hdf5``, ``.mat``) is read with
    ``sitk.ReadTransform`` and digested by
    :func:`itk_nrreval.io.transforms.transform_digest`; any other file SimpleITK reads as an
    image (incl. displacement fields) by :func:`itk_nrreval.io._images.image_digest` (pixel
    type, grid, voxel values; no header metadata); a file that reads as neither by its bytes.
    So the file and the same image or transform in memory have the same digest.

    Decoding costs a read of the file (about 0.2 s for a 1 mm brain volume, 0.7 s for its
    displacement field): each file's digest is kept for the process, under its path, size,
    modification and change times and inode, so a file that changes is decoded again.
    Header + data pairs (``.mhd``, ``.nhdr``) are decoded every time (their data file's
    changes do not show in the header's times), and so are elastix parameter files (read
    with their initial transforms' files, whose changes do not show in theirs).
    """
    from ._elastix_files import is_elastix_parameter_file
    from .transforms import file_suffix

    path = Path(path)
    if file_suffix(path) in (".mhd", ".nhdr") or is_elastix_parameter_file(path):
        return _decoded_digest(str(path))
    st = path.stat()
    return _cached_digest(
        str(path.resolve()), st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino
    )


@functools.lru_cache(maxsize=4096)
def _cached_digest(path: str, size: int, mtime_ns: int, ctime_ns: int, inode: int) -> str:
    return _decoded_digest(path)


def _decoded_digest(path: str) -> str:
    import SimpleITK as sitk

    from .._executors import ITK_READ_LOCK
    from ._elastix_files import is_elastix_parameter_file, read_elastix_transform
    from ._images import image_digest
    from .transforms import TRANSFORM_SUFFIXES, file_suffix, transform_digest

    if is_elastix_parameter_file(path):  # its initial transforms' files count too
        return transform_digest(read_elastix_transform(path))
    try:
        with ITK_READ_LOCK:
            if file_suffix(Path(path)) in TRANSFORM_SUFFIXES:
                read = sitk.ReadTransform(path)
            else:
                read = sitk.ReadImage(path)
        if isinstance(read, sitk.Transform):
            return transform_digest(read)
        return image_digest(read)
    except RuntimeError:  # not an image or transform: its bytes (a reader will say more)
        return "file:" + file_digest(path)


def digest_of(value: Any) -> str:
    """A stable digest of a JSON-like description of a computation.

    Paths (``pathlib.Path``) stand for their file's decoded content (:func:`content_digest`);
    SimpleITK images and transforms, and objects with a ``content_digest`` (a manifest's
    in-memory images and transforms), for their content, digested the same way -- so a file
    and the same image or transform in memory give the same digest; numpy arrays for their
    dtype, shape and bytes; lists, tuples and dicts recursively; other values by ``repr``.
    """
    h = hashlib.blake2b(digest_size=16)
    _feed(h, value)
    return h.hexdigest()


def _feed(h, value) -> None:
    import SimpleITK as sitk

    if isinstance(value, Path):
        h.update(b"content:" + content_digest(value).encode())
    elif isinstance(value, sitk.Image):
        from ._images import image_digest

        h.update(b"content:" + image_digest(value).encode())
    elif isinstance(value, sitk.Transform):
        from .transforms import transform_digest

        h.update(b"content:" + transform_digest(value).encode())
    elif isinstance(getattr(value, "content_digest", None), str):
        h.update(b"content:" + value.content_digest.encode())
    elif isinstance(value, np.ndarray):
        h.update(f"array:{value.dtype.str}:{value.shape}:".encode())
        h.update(np.ascontiguousarray(value).tobytes())
    elif isinstance(value, Mapping):
        h.update(b"{")
        for k in sorted(value):
            h.update(repr(k).encode() + b":")
            _feed(h, value[k])
            h.update(b",")
        h.update(b"}")
    elif isinstance(value, (list, tuple)):
        h.update(b"[")
        for v in value:
            _feed(h, v)
            h.update(b",")
        h.update(b"]")
    else:
        h.update(repr(value).encode())


def _tmp_suffix() -> str:
    return f".tmp-{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex}"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@dataclass(frozen=True)
class CacheEntry:
    """A verified entry: its folder and its metadata."""

    folder: Path
    meta: Mapping[str, Any]

    def array(self, name: str, *, mmap: bool = False) -> np.ndarray:
        """Load array `name` (memory-mapped read-only when `mmap`)."""
        # np.load's header parse is not thread-safe on CPython 3.11 (NPY_HEADER_LOCK):
        # headers are read one at a time, the data outside the lock
        with NPY_HEADER_LOCK:
            mapped = np.load(self.folder / f"{name}.npy", mmap_mode="r")
        return mapped if mmap else np.array(mapped)

    def has(self, name: str) -> bool:
        """Whether the entry holds array `name`."""
        return (self.folder / f"{name}.npy").is_file()


class DiskCache:
    """Entries by kind and key under `root` (created when missing).

    Parameters
    ----------
    root : path
        The cache folder. Several processes (and machines sharing the folder) may use it at
        once: each writes into its own temporary folder and renames it into place.
    """

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)
        self._lease: Path | None = None  # this run's mark, while in_use
        self._held_off: set[tuple[str, str]] = set()  # removals another run held off

    @contextlib.contextmanager
    def in_use(self) -> Iterator[DiskCache]:
        """Mark the cache as used by this run until the block ends.

        While another run's mark is alive, :meth:`remove` leaves entries in place (that run
        may have found them and be about to read them); they are removed when this block
        ends if this run is then alone. A mark is a file under ``.runs/`` locked (``flock``)
        by its process: a process that dies releases it, and the next run removes the file.
        """
        runs = self.root / ".runs"
        runs.mkdir(parents=True, exist_ok=True)
        with self._gate():
            lease = runs / f"{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex}"
            fd = os.open(lease, os.O_CREAT | os.O_RDWR, 0o644)
            fcntl.flock(fd, fcntl.LOCK_EX)
        self._lease = lease
        try:
            yield self
        finally:
            held_off, self._held_off = self._held_off, set()
            with self._gate():
                if self._alone():
                    for kind, key in sorted(held_off):
                        if self._folder(kind, key).is_dir():
                            self._discard(self._folder(kind, key))
                lease.unlink(missing_ok=True)
                os.close(fd)
                self._lease = None

    @contextlib.contextmanager
    def _gate(self) -> Iterator[None]:
        """Exclusive while a run registers its mark or removes entries (a few ms)."""
        self.root.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.root / ".gate", os.O_CREAT | os.O_RDWR, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            yield
        finally:
            os.close(fd)  # releases the lock

    def _alone(self) -> bool:
        """Whether no other run's mark is alive (under the gate); dead marks are removed."""
        for mark in (self.root / ".runs").glob("*"):
            if mark == self._lease:
                continue
            try:
                fd = os.open(mark, os.O_RDWR)
            except OSError:  # removed meanwhile by its run
                continue
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                return False
            else:
                mark.unlink(missing_ok=True)  # its process is gone
            finally:
                os.close(fd)
        return True

    def _folder(self, kind: str, key: str) -> Path:
        return self.root / kind / key[:2] / key

    def open(self, kind: str, key: str) -> CacheEntry:
        """An entry already verified by :meth:`get` in this run, opened without re-reading it."""
        folder = self._folder(kind, key)
        info = json.loads((folder / "entry.json").read_text())
        return CacheEntry(folder, info.get("meta", {}))

    def get(self, kind: str, key: str) -> CacheEntry | None:
        """The verified entry, or None when absent or corrupt (a corrupt one is removed)."""
        folder = self._folder(kind, key)
        if not folder.is_dir():
            return None
        try:
            info = json.loads((folder / "entry.json").read_text())
            if info.get("format") != _FORMAT or info.get("key") != key:
                raise ValueError("wrong format or key")
            for name, (digest, size) in info["arrays"].items():
                path = folder / f"{name}.npy"
                if path.stat().st_size != size or _file_crc32(path) != digest:
                    raise ValueError(f"{name}.npy does not match its CRC-32")
        except (OSError, ValueError, KeyError, TypeError):
            self._discard(folder)
            return None
        return CacheEntry(folder, info.get("meta", {}))

    def put(
        self,
        kind: str,
        key: str,
        arrays: Mapping[str, np.ndarray],
        meta: Mapping[str, Any] | None = None,
    ) -> CacheEntry:
        """Write an entry atomically (if another process wrote the same key first, keep it)."""
        folder = self._folder(kind, key)
        folder.parent.mkdir(parents=True, exist_ok=True)
        tmp = folder.parent / f"{key}{_tmp_suffix()}"
        tmp.mkdir()
        try:
            digests = {}
            for name, arr in arrays.items():
                path = tmp / f"{name}.npy"
                digests[name] = [_save_array(path, np.asarray(arr)), path.stat().st_size]
            info = {"format": _FORMAT, "key": key, "arrays": digests, "meta": dict(meta or {})}
            (tmp / "entry.json").write_text(json.dumps(info))
            try:
                os.rename(tmp, folder)
            except OSError:  # another process won the race, or a corrupt entry is in the way
                if self.get(kind, key) is None:
                    self._discard(folder)
                    os.rename(tmp, folder)
        finally:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)
        return CacheEntry(folder, dict(meta or {}))

    def remove(self, kind: str, key: str) -> None:
        """Remove an entry this run no longer needs (absent: nothing).

        While another run uses the cache (:meth:`in_use`), the entry stays: that run may
        have found it already. It is tried again when this run's :meth:`in_use` ends.
        """
        folder = self._folder(kind, key)
        if not folder.is_dir():
            return
        with self._gate():
            if self._alone():
                self._discard(folder)
                return
        self._held_off.add((kind, key))

    def remove_stale(self) -> int:
        """Remove temporary folders left by killed processes of this host; return how many.

        A temporary folder names its host and process id; folders of processes still alive,
        or of other hosts, are left alone.
        """
        host = socket.gethostname()
        removed = 0
        for tmp in self.root.glob("*/*/*.tmp-*"):
            parts = tmp.name.split(".tmp-", 1)[1].rsplit("-", 2)  # host, pid, random
            if len(parts) != 3 or parts[0] != host or not parts[1].isdigit():
                continue
            if _alive(int(parts[1])):
                continue
            shutil.rmtree(tmp, ignore_errors=True)
            removed += 1
        return removed

    @staticmethod
    def _discard(folder: Path) -> None:
        # Rename first so a reader never sees a half-deleted entry under the real name.
        trash = folder.with_name(f"{folder.name}{_tmp_suffix()}")
        try:
            os.rename(folder, trash)
        except OSError:
            return
        shutil.rmtree(trash, ignore_errors=True)
