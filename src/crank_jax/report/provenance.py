"""Where a report's result came from: package versions, the command line, the scene as
TOML, the data files' names and SHA-256, and the time."""

from __future__ import annotations

import datetime
import hashlib
import importlib.metadata
import os
import shlex
import sys
from collections.abc import Sequence

__all__ = ["provenance", "sha256_file", "scene_toml", "VERSIONED"]

#: The distributions whose versions a report names.
VERSIONED = ("crank-jax", "jax", "jaxlib", "diffrax", "equinox", "optimistix", "numpy")


def sha256_file(path: str | os.PathLike) -> str:
    """Hex SHA-256 of a file's bytes, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _version(dist: str) -> str:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return "not installed"


def scene_toml(scene) -> str:
    """The scene as the TOML that `load_scene` reads, or a sentence saying why it cannot be
    written (a load kind that a scene file cannot hold)."""
    from ..scene import scene_to_toml

    try:
        return scene_to_toml(scene)
    except ValueError as e:
        return f"# not expressible as a scene file: {e}"


def _files(sources: Sequence[str]) -> list[dict]:
    out = []
    for s in dict.fromkeys(sources):  # in order, once each
        if os.path.isfile(s):
            out.append({"name": s, "sha256": sha256_file(s), "bytes": os.path.getsize(s)})
        else:
            out.append({"name": s, "sha256": None, "bytes": None})
    return out


def provenance(*, command: Sequence[str] | str | None, scene, sources: Sequence[str],
               fitted=None) -> dict:
    """The provenance section of a report.

    **Arguments:** `command`: the command line (argv without the program, or a string;
    `None`: this process's `sys.argv`); `scene`: the scene the run started from, or
    `None`; `sources`: the records' labels (a file's path is hashed, other labels are
    listed as they are); `fitted`: the fitted scene, or `None`.

    **Returns:** a dict of plain strings and lists for the template.
    """
    if command is None:
        command = [os.path.basename(sys.argv[0])] + sys.argv[1:]
    if not isinstance(command, str):
        command = shlex.join(str(c) for c in command)
    now = datetime.datetime.now(datetime.UTC)
    return {
        "versions": {d: _version(d) for d in VERSIONED},
        "python": sys.version.split()[0],
        "command": command,
        "cwd": os.getcwd(),
        "time": now.isoformat(timespec="seconds"),
        "scene": None if scene is None else scene_toml(scene),
        "fitted_scene": None if fitted is None else scene_toml(fitted),
        "files": _files(list(sources)),
    }
