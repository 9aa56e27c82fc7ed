"""The files of the compiled-program store (see `persistent.py`): their format, a checked
read, an atomic write, and the eviction of the least recently used; and the executables
loaded from it in memory, as few as a process can hold ([`LoadedPrograms`][]).

A stored program is one file, `<name>-<key prefix>.xla`, made of

    MAGIC | key (64 ASCII hex digits) | outputs (4 bytes, little-endian)
          | calls LAPACK (1 byte) | devices (1 byte) | JAX's serialisation
          | SHA-256 of everything before it (32 bytes)

The digest covers the whole file and is checked before any of it is used: a flipped bit
anywhere (header, executable, digest), a truncated or extended file, or an intact file
under another key's name is a miss, and the file is discarded; the caller then compiles
the program again and stores it anew. (Without the digest a damaged executable was loaded
and gave wrong numbers with exit 0, or crashed the process, on every later run.)
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import stat
import threading
import time
from collections import OrderedDict
from pathlib import Path
from typing import NamedTuple

from .io import remove_stale_temps, temp_file

__all__ = ["Entry", "pack", "unpack", "read", "write", "discard", "evict", "MAGIC",
           "MAX_PROGRAMS", "STALE_TEMP_S", "LoadedPrograms", "LOADED"]

#: The format's tag; a new layout gets a new number (older files are then misses).
MAGIC = b"crank-jax program 4\n"
_KEY = 64  # a SHA-256 in hex
_HEAD = len(MAGIC) + _KEY + 6
_DIGEST = 32

#: The store keeps at most this many programs (~1 MB each), the most recently used.
MAX_PROGRAMS = 256

#: A temporary file of the store untouched for this long (s) belongs to a writer that
#: died (a write takes milliseconds), wherever it ran, and is removed by the next
#: eviction (one of a dead process of this host at once, see `io.remove_stale_temps`).
STALE_TEMP_S = 600.0


class Entry(NamedTuple):
    """A stored program's header and JAX's serialised executable."""

    n_out: int  # outputs (a flat tuple of arrays)
    lapack: bool  # whether it calls LAPACK (its targets must be registered first)
    n_dev: int  # devices it runs on
    payload: bytes  # `jax.experimental.serialize_executable.serialize(...)[0]`


def pack(key: str, entry: Entry) -> bytes:
    """The file's bytes for `entry` stored under `key` (64 hex digits)."""
    if len(key) != _KEY or not 0 <= entry.n_out < 2**32 or not 0 <= entry.n_dev < 256:
        raise ValueError("cannot store this program")
    body = (MAGIC + key.encode("ascii") + entry.n_out.to_bytes(4, "little")
            + bytes([bool(entry.lapack), entry.n_dev]) + entry.payload)
    return body + hashlib.sha256(body).digest()


def unpack(blob: bytes, key: str) -> Entry:
    """The entry in a file's bytes, checked whole against its digest and `key`;
    `ValueError` for anything else (damaged, truncated, extended, foreign, another key)."""
    body, digest = blob[:-_DIGEST], blob[-_DIGEST:]
    if (len(blob) < _HEAD + _DIGEST or hashlib.sha256(body).digest() != digest
            or not body.startswith(MAGIC)
            or body[len(MAGIC):len(MAGIC) + _KEY] != key.encode("ascii")):
        raise ValueError("not an intact stored program")
    head = body[len(MAGIC) + _KEY:_HEAD]
    return Entry(int.from_bytes(head[:4], "little"), bool(head[4]), head[5],
                 body[_HEAD:])


def read(path: Path, key: str) -> Entry | None:
    """The intact entry stored at `path` under `key`, or None: missing, not a regular
    file (a symbolic link, a FIFO: never followed or waited on), or damaged (then
    discarded). A hit marks the file recently used (kept by [`evict`][])."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except OSError:
        return None
    try:
        with os.fdopen(fd, "rb") as f:
            if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
                return None
            blob = f.read()
            with contextlib.suppress(OSError):
                os.utime(f.fileno())
    except OSError:
        return None
    try:
        return unpack(blob, key)
    except ValueError:
        discard(path)
        return None


def discard(path: Path) -> None:
    """Remove a stored program that must not be loaded (damaged, or one that failed)."""
    with contextlib.suppress(OSError):
        os.unlink(path)


def write(path: Path, blob: bytes) -> None:
    """Store `blob` at `path` atomically: a temporary file beside it, renamed over it
    (whatever is there: a damaged file, a link or a FIFO is replaced, never written
    through). A store that cannot be written is not an error. Then [`evict`][]."""
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = temp_file(path.parent, path.name)
        with os.fdopen(fd, "wb") as f:
            f.write(blob)
        # No fsync: a store is a cache, and a file torn by a power loss fails its digest.
        os.replace(tmp, path)
        tmp = None
        evict(path.parent)
    except OSError:
        pass
    finally:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)


def evict(store: Path) -> None:
    """Remove the least recently used programs beyond [`MAX_PROGRAMS`][], and temporary
    files left by a writer that was killed (its process is gone, or the file is older
    than [`STALE_TEMP_S`][]). Only regular files count: a dangling link or anything else
    named `*.xla` is skipped, never fatal."""
    remove_stale_temps(store)
    programs, now = [], time.time()
    try:
        entries = list(os.scandir(store))
    except OSError:
        return
    for e in entries:
        try:
            st = e.stat(follow_symlinks=False)
        except OSError:
            continue
        if not stat.S_ISREG(st.st_mode):
            continue
        if e.name.endswith(".xla"):
            programs.append((st.st_mtime, e.path))
        elif e.name.startswith(".") and e.name.endswith(".tmp") and (
                now - st.st_mtime > STALE_TEMP_S):
            discard(Path(e.path))
    programs.sort()
    for _, p in programs[:max(0, len(programs) - MAX_PROGRAMS)]:
        discard(Path(p))


class LoadedPrograms:
    """The executables the programs of this process loaded or compiled, at most `limit`,
    over all programs: the least recently called goes first (and is loaded from the
    store again if it is called again). Each holds a couple of hundred memory mappings of
    machine code (about 210 for a crank solve on XLA:CPU) and Linux refuses a process more
    than `vm.max_map_count` (65530 by default): about 300 kept at once, and XLA aborts the
    process in its next compile.

    Keyed by `(program, key)`: each program object keeps its own, as when each held its
    own dict (a second object of the same name loads from the store, as a fresh process
    does). Thread-safe: `fit_many` calls programs from two threads, and one thread's
    eviction between another's lookup and its `move_to_end` would be a `KeyError`."""

    def __init__(self, limit: int):
        self.limit = limit
        self._calls: OrderedDict = OrderedDict()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._calls)

    def get(self, key):
        with self._lock:
            call = self._calls.get(key)
            if call is not None:
                self._calls.move_to_end(key)
            return call

    def put(self, key, call) -> None:
        with self._lock:
            self._calls[key] = call
            self._calls.move_to_end(key)
            while len(self._calls) > self.limit:
                self._calls.popitem(last=False)


#: Every `PersistentProgram`'s loaded executables (see [`LoadedPrograms`][]).
LOADED = LoadedPrograms(96)
