"""Safe file output: atomic writes that never clobber an input file."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO

__all__ = ["atomic_write", "check_not_input"]


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "w") -> Iterator[IO]:
    """Open a temporary file beside `path`; on success rename it over `path` atomically.

    A crash or an exception leaves `path` as it was (no half-written files). The rename is
    `os.replace`, atomic on POSIX and Windows when both are on one file system, which the
    temporary file beside the target guarantees.
    """
    path = Path(path)
    directory = path.parent if str(path.parent) else Path(".")
    if not directory.is_dir():
        raise FileNotFoundError(f"output directory {str(directory)!r} does not exist")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=directory)
    try:
        with os.fdopen(fd, mode) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def check_not_input(out: str | os.PathLike, inputs: list[str | os.PathLike | None]) -> None:
    """Raise `ValueError` if the output path is one of the input files."""
    o = Path(out).resolve()
    for i in inputs:
        if i is not None and Path(i).exists() and Path(i).resolve() == o:
            raise ValueError(
                f"output {str(out)!r} is an input file; refusing to overwrite it: choose "
                "another --out"
            )
