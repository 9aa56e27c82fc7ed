"""Safe file output: atomic writes with the umask's permissions that never clobber an input
file, and checks of output paths made before any work."""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import re
import socket
import stat
import tempfile
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import IO

__all__ = ["atomic_write", "make_dir", "check_input", "check_not_input", "check_output",
           "check_figure_format", "default_file_mode", "Terminated", "note_signal",
           "raise_if_terminated", "temp_file", "remove_stale_temps", "STALE_TEMP_S",
           "DISK_FULL", "disk_full", "printable", "read_only", "same_file",
           "check_distinct_outputs"]


class Terminated(BaseException):
    """Raised in the main thread by SIGTERM or SIGHUP (under the CLI), so that `finally`
    blocks and the atomic writers' cleanup run; a BaseException like KeyboardInterrupt, so
    that no `except Exception` swallows it."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


# Signals received (by the CLI's handler) in this process. Python drops an exception that
# a signal handler raises while a garbage-collector callback or a `__del__` runs (JAX
# registers such a callback), so the handler also notes the signal here, and a writer
# checks before it commits: a terminated run never replaces an output.
_SIGNALS: list[int] = []


def note_signal(signum: int | None) -> None:
    """Record a received signal (`None` forgets them all)."""
    if signum is None:
        _SIGNALS.clear()
    else:
        _SIGNALS.append(signum)


def raise_if_terminated() -> None:
    """Raise [`Terminated`][] if a signal was noted whose exception may have been lost."""
    if _SIGNALS:
        raise Terminated(_SIGNALS[0])


def printable(text: str) -> str:
    """`text` as valid Unicode: a file name that is not UTF-8 reaches Python with its bad
    bytes as lone surrogates (`'\\udcff'`), which no UTF-8 file and no font takes; each
    is shown as its byte, `\\xff` (other lone surrogates as `\\udXXX`)."""
    try:
        raw = text.encode("utf-8", "surrogateescape")
    except UnicodeEncodeError:
        raw = text.encode("utf-8", "backslashreplace")
    return raw.decode("utf-8", "backslashreplace")


def default_file_mode() -> int:
    """The mode `open(path, "w")` gives a new file: `0o666` less the process's umask."""
    # os.umask can only be read by setting it; set it back at once (the CLI is
    # single-threaded while it writes files).
    mask = os.umask(0o022)
    os.umask(mask)
    return 0o666 & ~mask


def read_only(path: str | os.PathLike) -> bool:
    """Whether `path` is an existing regular file that is read-only: it has no write
    permission bit at all, or none that this process holds. The bits are read, not only
    `os.access`: root passes `os.access` on any file, yet a file made read-only is its
    owner's way of saying "keep this", whoever runs the writer."""
    try:
        st = os.stat(path)
    except OSError:
        return False
    if not stat.S_ISREG(st.st_mode):
        return False
    return not st.st_mode & (stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH) or not os.access(
        path, os.W_OK)


def _read_only_error(path: Path) -> PermissionError:
    err = PermissionError(f"output {str(path)!r} exists and is read-only; choose another "
                          "name or make it writable")
    err.errno = errno.EACCES
    return err


def _is_special(path: Path) -> bool:
    """True for an existing file that is not a regular file (a device, a FIFO, a socket)."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return False
    return not stat.S_ISREG(mode) and not stat.S_ISDIR(mode)


#: A temporary file untouched for this long (s) is a dead writer's, wherever it ran.
STALE_TEMP_S = 3600.0
_HOST = hashlib.sha256(socket.gethostname().encode()).hexdigest()[:8]
_TEMP = r"\.(\d+)\.([0-9a-f]{8})-\w+\.tmp"  # after `.{name}`: `.{pid}.{host}-{random}.tmp`


def temp_file(directory: Path, name: str) -> tuple[int, str]:
    """`tempfile.mkstemp` for a file `name` in `directory`, named after this process
    (`.{name}.{pid}.{host}-{random}.tmp`) so that a later writer can tell a dead writer's
    file from a live one; removes the stale ones of `name` first
    ([`remove_stale_temps`][]). A process killed (SIGKILL, a crash) before it renames or
    removes its file leaves it only until the next write of the same name."""
    remove_stale_temps(directory, name)
    return tempfile.mkstemp(prefix=f".{name}.{os.getpid()}.{_HOST}-", suffix=".tmp",
                            dir=directory)


def remove_stale_temps(directory: Path, name: str | None = None) -> None:
    """Remove the [`temp_file`][]s of `name` (any name if None) whose writer is gone: a
    process of this host that no longer runs, or a file untouched for
    [`STALE_TEMP_S`][]. Never an error."""
    pattern = re.compile((re.escape(f".{name}") if name is not None else r"\..+") + _TEMP)
    now = time.time()
    try:
        entries = list(os.scandir(directory))
    except OSError:
        return
    for e in entries:
        m = pattern.fullmatch(e.name)
        with contextlib.suppress(OSError):
            if m and e.is_file(follow_symlinks=False) and (
                    (m[2] == _HOST and not _alive(int(m[1])))
                    or now - e.stat(follow_symlinks=False).st_mtime > STALE_TEMP_S):
                os.unlink(e.path)


def _alive(pid: int) -> bool:
    """Whether process `pid` runs on this host (one of another user counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, ValueError):
        return True
    return True


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISSOCK, "a socket"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device")):
        if test(mode):
            return name
    return "not a regular file"


def make_dir(path: Path, label: str) -> None:
    """Create the directory `path` (and its parents) if missing; `ValueError` naming
    `label` (the option or argument) and the system's reason when it cannot be."""
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ValueError(f"{label} {str(path)!r}: cannot create the directory "
                         f"({e.strerror})") from None


def check_input(path: str | os.PathLike, option: str = "input") -> None:
    """Raise `ValueError` naming `option` unless `path` is a regular file (`OSError` if it
    does not exist or cannot be looked at).

    Checked without opening it: opening a FIFO with no writer waits forever, and a device
    such as /dev/zero or /dev/stdin never ends or can be read only once. A symbolic link
    is followed.
    """
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise FileNotFoundError(f"{option} {str(path)!r} does not exist") from None
    except OSError as e:
        raise OSError(f"{option} {str(path)!r} cannot be read: {e.strerror}") from None
    if not stat.S_ISREG(mode):
        raise ValueError(f"{option} {str(path)!r} is {_kind(mode)}, not a regular file; save "
                         "its content to a file and name that")


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "w") -> Iterator[IO]:
    """Open a temporary file beside `path`; on success rename it over `path` atomically.

    A crash, an exception, Ctrl-C or (under the CLI, which turns it into an exception)
    SIGTERM leaves `path` as it was and removes the temporary file. The rename is
    `os.replace`, atomic on POSIX and Windows when both are on one file system, which the
    temporary file beside the target guarantees. The file gets the permissions `open`
    would give: an existing file's mode, else `0o666` less the umask. A symbolic link is
    written through (its target is replaced), and an existing device or FIFO such as
    `/dev/null` is written to directly, never replaced. An existing read-only file
    ([`read_only`][], by its mode bits, also for root) is never replaced:
    `PermissionError`, before anything is written.
    """
    path = Path(path)
    if path.is_symlink():
        path = Path(os.path.realpath(path))
    if _is_special(path):
        with open(path, mode) as f:
            yield f
        return
    if path.is_dir():
        raise IsADirectoryError(f"output {str(path)!r} is a directory; name a file")
    if read_only(path):
        raise _read_only_error(path)
    directory = path.parent if str(path.parent) else Path(".")
    if not directory.is_dir():
        raise FileNotFoundError(f"output directory {str(directory)!r} does not exist")
    try:
        file_mode = stat.S_IMODE(os.stat(path).st_mode)
    except OSError:
        file_mode = default_file_mode()
    fd, tmp = temp_file(directory, path.name)
    try:
        with os.fdopen(fd, mode) as f:
            os.fchmod(f.fileno(), file_mode)
            yield f
            f.flush()
            os.fsync(f.fileno())
        raise_if_terminated()
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if isinstance(e, OSError) and e.errno in DISK_FULL:
            raise disk_full(path, e) from None
        raise


#: The errors of a write that found no space: the disk is full, or the user's quota.
DISK_FULL = (errno.ENOSPC, errno.EDQUOT)


def disk_full(path: str | os.PathLike | None, e: OSError) -> OSError:
    """The one-line error of a write to `path` that found no space (`e`, ENOSPC or EDQUOT):
    what could not be written, that the disk is full, and that an existing file of that
    name was left as it was (the writers write beside it and rename)."""
    what = f"{str(path)!r}" if path is not None else "an output"
    where = "the disk quota is used up" if e.errno == errno.EDQUOT else "the disk is full"
    err = OSError(f"could not write {what}: {where} ({e.strerror}); nothing was replaced "
                  f"(an existing {what} is unchanged): free some space and run again")
    err.errno = e.errno
    return err


def check_not_input(out: str | os.PathLike, inputs: Sequence[str | os.PathLike | None],
                    option: str = "output path") -> None:
    """Raise `ValueError` if the output path is one of the input files (`option`: what
    names the path to the user, e.g. the CLI's `--out`)."""
    o = Path(out).resolve()
    for i in inputs:
        if i is not None and Path(i).exists() and Path(i).resolve() == o:
            raise ValueError(
                f"output {str(out)!r} is an input file; refusing to overwrite it: choose "
                f"another {option}"
            )


def check_output(out: str | os.PathLike, inputs: Sequence[str | os.PathLike | None] = (),
                 option: str = "output path") -> None:
    """Check an output path before any work: not an input, not a directory, in an existing
    writable directory. Raises `ValueError` naming `option` and the fix."""
    text = str(out)
    if not text or text.endswith(os.sep):
        raise ValueError(f"{option} {text!r} is not a file name; name a file")
    check_not_input(out, inputs, option)
    path = Path(out)
    if path.is_symlink():
        path = Path(os.path.realpath(path))
    if path.is_dir():
        raise ValueError(f"{option} {text!r} is a directory; name a file in it")
    if _is_special(path):
        return
    directory = path.parent if str(path.parent) else Path(".")
    if not directory.is_dir():
        raise ValueError(f"{option} {text!r}: output directory {str(directory)!r} does not "
                         "exist; create it first")
    if not os.access(directory, os.W_OK | os.X_OK):
        raise ValueError(f"{option} {text!r}: cannot write in directory {str(directory)!r} "
                         "(permission denied); choose another place")
    if read_only(path):
        # os.replace would succeed anyway (it needs only the directory), but a read-only
        # file is a user's way of saying "keep this".
        raise ValueError(f"{option} {text!r} exists and is read-only; choose another name "
                         "or make it writable")


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Whether two paths name one file: the same inode when both exist (a hard link, a
    case-insensitive file system), else the same path once symbolic links, `.` and `..`
    are resolved (`./x` is `x`; a link is its target, even one not yet written)."""
    with contextlib.suppress(OSError):
        if os.path.exists(a) and os.path.exists(b):
            return os.path.samefile(a, b)
    return (os.path.normcase(os.path.realpath(a)) == os.path.normcase(os.path.realpath(b)))


def check_distinct_outputs(outputs: Sequence[tuple[str | os.PathLike | None, str]]) -> None:
    """Raise `ValueError` naming both options when two of `outputs` (`(path, option)`
    pairs; a `None` path is skipped) are one file ([`same_file`][]): the one written last
    would replace the other. Call it before any work."""
    named = [(p, o) for p, o in outputs if p is not None and str(p)]
    for i, (p1, o1) in enumerate(named):
        for p2, o2 in named[i + 1:]:
            if same_file(p1, p2):
                raise ValueError(f"{o2} {str(p2)!r} is the same file as {o1} {str(p1)!r}; "
                                 "give each output its own file")


def check_figure_format(path: str | os.PathLike, option: str = "figure") -> None:
    """Raise `ValueError` unless matplotlib can write `path`'s format (from its suffix)."""
    from matplotlib.figure import Figure

    fmt = os.path.splitext(str(path))[1].lstrip(".").lower() or "png"
    # pgf needs a LaTeX installation that we cannot check without running it.
    formats = sorted(set(Figure().canvas.get_supported_filetypes()) - {"pgf"})
    if fmt not in formats:
        raise ValueError(f"{option} {str(path)!r}: format {fmt!r} is not supported; use a "
                         f"suffix from {', '.join(formats)}")
