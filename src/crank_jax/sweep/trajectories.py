"""Saved trajectories of a sweep, streamed to disk chunk by chunk and read lazily.

Format (a directory): `manifest.json` and, per finished chunk, three `.npy` files, each
written atomically: `chunk-B-S.phi.npy` and `chunk-B-S.dphi.npy`, (m, n_t) float64 (rad,
rad/s) at the save times `ts[::every]`, and `chunk-B-S.idx.npy`, (m,) int64, the samples'
indices in the sweep's order (chunks hold samples sorted by stiffness, see `run.py`).
Written last, the index file marks the chunk as done. The manifest holds the plan (as a
checkpoint's), `every`, the saved times, `n` and, once the sweep has finished,
`"complete": true` and the list of chunks. Samples whose status is not `"ok"` hold 0 (as
in the result), and invalid samples, never solved, have no row.

Why `.npy` files and not zarr or parquet: `np.load(path, mmap_mode="r")` reads them
lazily with NumPy alone (no new dependency), each chunk is one atomic file, which is what
a resumed sweep needs (a chunk is there whole or not at all), and a trajectory is a dense
float64 block, which gains nothing from parquet's columns. [`Trajectories`][] is the
reader.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..io import atomic_write, make_dir

__all__ = ["TrajectoryStore", "Trajectories", "load_trajectories", "FIELDS"]

FIELDS = ("phi", "dphi")
_MANIFEST = "manifest.json"
_FORMAT = "crank-jax sweep trajectories 1"


def _gigabytes(b: float) -> str:
    return f"{b / 1e9:.3g} GB"


class TrajectoryStore:
    """The writer (process 0 of a run; see the module docstring).

    `path`: the directory (created if missing); `plan_manifest`: the plan's description
    (`checkpoint.plan_manifest`); `ts`: (n_t,) the sweep's save times, s; `every`: keep
    every `every`-th of them; `n`: the number of samples. Refuses (`ValueError`, one line)
    a directory that is a file, holds another sweep's trajectories, or whose disk has less
    free space than the trajectories need.
    """

    def __init__(self, path, plan_manifest: dict, ts: np.ndarray, every: int, n: int):
        if int(every) < 1:
            raise ValueError(f"save_trajectories: every must be >= 1, got {every}")
        self.dir, self.every = Path(path), int(every)
        self.ts = np.asarray(ts)[::self.every]
        if self.dir.exists() and not self.dir.is_dir():
            raise ValueError(f"save_trajectories {str(self.dir)!r} is a file, not a "
                             "directory; give a directory (it is created if missing)")
        need = n * (len(FIELDS) * self.ts.size + 1) * 8
        probe = self.dir if self.dir.exists() else self.dir.parent
        while not probe.exists() and probe != probe.parent:
            probe = probe.parent
        free = shutil.disk_usage(probe).free
        if need > free:
            raise ValueError(
                f"save_trajectories: {n} samples x {self.ts.size} times x {len(FIELDS)} "
                f"fields need {_gigabytes(need)}, more than the {_gigabytes(free)} free at "
                f"{str(probe)!r}; keep fewer times (every > {self.every}), fewer samples "
                "or another disk")
        make_dir(self.dir, "save_trajectories")
        self.head = {"format": _FORMAT, "plan": plan_manifest, "every": self.every,
                     "ts": self.ts.tolist(), "n": int(n), "fields": list(FIELDS),
                     "units": {"phi": "rad", "dphi": "rad/s", "ts": "s"}}
        path = self.dir / _MANIFEST
        if path.exists():
            try:
                have = json.loads(path.read_text())
            except (OSError, ValueError):
                have = {}
            differ = [k for k in self.head if have.get(k) != self.head[k]]
            if differ:
                raise ValueError(f"save_trajectories {str(self.dir)!r} holds another "
                                 f"sweep's trajectories: its {', '.join(differ)} differ; "
                                 "give another directory, or delete it")
        self._manifest(complete=False)
        #: (block start, chunk start) of every chunk of the sweep, in order.
        self.chunks: list[tuple[int, int]] = []

    def _manifest(self, complete: bool, chunks: list[str] | None = None) -> None:
        with atomic_write(self.dir / _MANIFEST, "w") as f:
            json.dump(self.head | {"complete": complete, "chunks": chunks or []}, f)

    def _stem(self, b0: int, start: int) -> str:
        return f"chunk-{b0}-{start}"

    def has(self, b0: int, start: int, idx: np.ndarray) -> bool:
        """Whether chunk (b0, start) is saved whole for the samples `idx` (into the block)."""
        stem = self.dir / self._stem(b0, start)
        try:
            saved = np.load(f"{stem}.idx.npy", mmap_mode="r")
            shapes = [np.load(f"{stem}.{k}.npy", mmap_mode="r").shape for k in FIELDS]
        except (OSError, ValueError):
            return False
        return (np.array_equal(saved, b0 + np.asarray(idx))
                and all(s == (idx.size, self.ts.size) for s in shapes))

    def save(self, b0: int, start: int, idx: np.ndarray, res: dict) -> None:
        """Write one chunk: `res["phi"]`, `res["dphi"]` (m, n_t of the sweep)."""
        stem = self._stem(b0, start)
        for k in FIELDS:
            with atomic_write(self.dir / f"{stem}.{k}.npy", "wb") as f:
                np.save(f, np.ascontiguousarray(np.asarray(res[k])[:, ::self.every]))
        with atomic_write(self.dir / f"{stem}.idx.npy", "wb") as f:
            np.save(f, (b0 + np.asarray(idx)).astype(np.int64))

    def finish(self) -> None:
        """Mark the store complete, listing its chunks in order."""
        self._manifest(complete=True, chunks=[self._stem(*c) for c in self.chunks])


class Trajectories:
    """Lazy reader of a directory written by a sweep with `save_trajectories=`.

    **Fields:** `ts` (n_t,) save times, s; `n`: number of samples of the sweep;
    `manifest`: the whole manifest. Nothing is read until asked for; arrays are
    memory-mapped (`np.load(mmap_mode="r")`).
    """

    def __init__(self, path):
        self.dir = Path(path)
        try:
            self.manifest = json.loads((self.dir / _MANIFEST).read_text())
        except (OSError, ValueError) as e:
            raise ValueError(f"{str(self.dir)!r} holds no saved trajectories "
                             f"({_MANIFEST}: {e})") from None
        if self.manifest.get("format") != _FORMAT:
            raise ValueError(f"{str(self.dir)!r}: {_MANIFEST} is not a crank-jax "
                             "trajectory manifest")
        if not self.manifest.get("complete"):
            raise ValueError(f"{str(self.dir)!r}: the sweep writing these trajectories has "
                             "not finished; rerun it (with a checkpoint only the missing "
                             "chunks are computed)")
        self.ts = np.asarray(self.manifest["ts"])
        self.n = int(self.manifest["n"])
        self._index = None

    def chunks(self) -> Iterator[tuple[np.ndarray, dict[str, np.ndarray]]]:
        """Yield `(idx, {"phi": (m, n_t), "dphi": (m, n_t)})` per chunk, memory-mapped;
        `idx` (m,): the rows' sample indices."""
        for stem in self.manifest["chunks"]:
            base = self.dir / stem
            yield (np.load(f"{base}.idx.npy"),
                   {k: np.load(f"{base}.{k}.npy", mmap_mode="r") for k in FIELDS})

    def __getitem__(self, samples) -> dict[str, np.ndarray]:
        """The trajectories of sample indices `samples` (an int or an array of them), as
        `{"phi", "dphi"}` arrays of shape (..., n_t). A sample that was never solved
        (status `"invalid"`) raises `KeyError`."""
        if self._index is None:
            # Where each sample's row lives: (chunk number, row), built on first use from
            # the index files alone (8 bytes per sample each).
            self._index = np.full((self.n, 2), -1, np.int64)
            for c, stem in enumerate(self.manifest["chunks"]):
                idx = np.load(self.dir / f"{stem}.idx.npy")
                self._index[idx] = np.stack([np.full(idx.size, c), np.arange(idx.size)], 1)
        want = np.asarray(samples)
        where = self._index[want.reshape(-1)]
        if (where[:, 0] < 0).any():
            raise KeyError(f"samples {want.reshape(-1)[where[:, 0] < 0][:5].tolist()} have "
                           "no trajectory (invalid: never solved)")
        out = {k: np.empty((where.shape[0], self.ts.size)) for k in FIELDS}
        for c in np.unique(where[:, 0]):
            rows = where[:, 0] == c
            base = self.dir / self.manifest["chunks"][c]
            for k in FIELDS:
                out[k][rows] = np.load(f"{base}.{k}.npy", mmap_mode="r")[where[rows, 1]]
        return {k: v.reshape(*want.shape, self.ts.size) for k, v in out.items()}


def load_trajectories(path: str | os.PathLike) -> Trajectories:
    """Open the trajectories a sweep saved in `path` (`save_trajectories=`), lazily:
    see [`Trajectories`][]."""
    return Trajectories(path)
