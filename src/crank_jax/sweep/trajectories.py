"""Saved trajectories of a sweep, streamed to disk chunk by chunk and read lazily.

Format (a directory): `manifest.json` and, per finished chunk, three `.npy` files, each
written atomically: `chunk-B-S.phi.npy` and `chunk-B-S.dphi.npy`, (m, n_t) float64 (rad,
rad/s) at the save times `ts[::every]`, and `chunk-B-S.idx.npy`, (m,) int64, the samples'
indices in the sweep's order (chunks hold samples sorted by stiffness, see `run.py`).
Written last, `chunk-B-S.sha256.json` marks the chunk as done: the SHA-256 of each of the
three files, bound to the plan's digest, the chunk and the field (a damaged file, one of
another chunk or field swapped in, or one of another sweep fails it). The reader checks a
chunk's files before returning anything from them (`ValueError` naming the file), and a
resumed sweep computes such a chunk again. The manifest holds the plan (as a
checkpoint's), `every`, the saved times, `n` and, once the sweep has finished,
`"complete": true` and the list of chunks, and `"sha256"`, the SHA-256 of all the rest
(an edited `ts`, `n` or chunk list would change what the reader serves: it refuses a
manifest whose checksum does not match). Samples whose status is not `"ok"` hold 0 (as
in the result), and invalid samples, never solved, have no row.

Why `.npy` files and not zarr or parquet: `np.load(path, mmap_mode="r")` reads them
lazily with NumPy alone (no new dependency), each chunk is one atomic file, which is what
a resumed sweep needs (a chunk is there whole or not at all), and a trajectory is a dense
float64 block, which gains nothing from parquet's columns. [`Trajectories`][] is the
reader.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..runtime.io import atomic_write, make_dir
from .checkpoint import plan_digest

__all__ = ["TrajectoryStore", "Trajectories", "load_trajectories", "FIELDS"]

FIELDS = ("phi", "dphi")
_MANIFEST = "manifest.json"
# 2: with per-chunk checksums; 3: the manifest checksummed too
_FORMAT = "crank-jax sweep trajectories 3"
_OLDER = ("crank-jax sweep trajectories 1", "crank-jax sweep trajectories 2")
_SUMS = "sha256.json"  # a chunk's checksums: f"{stem}.{_SUMS}"


def _file_digest(plan: str, stem: str, key: str, data: bytes) -> str:
    """SHA-256 of one saved file's bytes, bound to the plan, its chunk and its field."""
    h = hashlib.sha256(f"{plan}\0{stem}.{key}\0".encode())
    h.update(data)
    return h.hexdigest()


def _manifest_digest(doc: dict) -> str:
    """SHA-256 of a manifest's every entry but its own checksum, in a canonical JSON
    form (the same after a round trip through `json`)."""
    body = {k: v for k, v in doc.items() if k != "sha256"}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=True)
    return hashlib.sha256(text.encode()).hexdigest()


def _npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a)
    return buf.getvalue()


def _check_chunk(directory: Path, plan: str, stem: str, keys=FIELDS + ("idx",)) -> None:
    """`ValueError` unless chunk `stem`'s files `keys` match its checksums."""
    try:
        sums = json.loads((directory / f"{stem}.{_SUMS}").read_text())
    except (OSError, ValueError):
        sums = None
    if not isinstance(sums, dict):
        raise ValueError(f"saved trajectories {str(directory / stem)!r}: checksums missing "
                         "or unreadable; rerun the sweep (with its checkpoint only this "
                         "chunk is computed again)")
    for k in keys:
        path = directory / f"{stem}.{k}.npy"
        try:
            ok = sums.get(k) == _file_digest(plan, stem, k, path.read_bytes())
        except OSError:
            ok = False
        if not ok:
            raise ValueError(f"saved trajectories {str(path)!r} are damaged or not this "
                             "chunk's (checksum mismatch); rerun the sweep (with its "
                             "checkpoint only this chunk is computed again)")


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
        self.plan = plan_digest(plan_manifest)
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
        doc = self.head | {"complete": complete, "chunks": chunks or []}
        with atomic_write(self.dir / _MANIFEST, "w") as f:
            json.dump(doc | {"sha256": _manifest_digest(doc)}, f)

    def _stem(self, b0: int, start: int) -> str:
        return f"chunk-{b0}-{start}"

    def has(self, b0: int, start: int, idx: np.ndarray) -> bool:
        """Whether chunk (b0, start) is saved whole and intact (its checksums) for the
        samples `idx` (into the block)."""
        stem = self._stem(b0, start)
        try:
            _check_chunk(self.dir, self.plan, stem)
            base = self.dir / stem
            saved = np.load(f"{base}.idx.npy", mmap_mode="r")
            shapes = [np.load(f"{base}.{k}.npy", mmap_mode="r").shape for k in FIELDS]
        except (OSError, ValueError):
            return False
        return (np.array_equal(saved, b0 + np.asarray(idx))
                and all(s == (idx.size, self.ts.size) for s in shapes))

    def save(self, b0: int, start: int, idx: np.ndarray, res: dict) -> None:
        """Write one chunk: `res["phi"]`, `res["dphi"]` (m, n_t of the sweep), then its
        checksums (last: they mark the chunk as done)."""
        stem = self._stem(b0, start)
        arrays = {k: np.ascontiguousarray(np.asarray(res[k])[:, ::self.every])
                  for k in FIELDS}
        arrays["idx"] = (b0 + np.asarray(idx)).astype(np.int64)
        sums = {}
        for k, a in arrays.items():
            data = _npy_bytes(a)
            sums[k] = _file_digest(self.plan, stem, k, data)
            with atomic_write(self.dir / f"{stem}.{k}.npy", "wb") as f:
                f.write(data)
        with atomic_write(self.dir / f"{stem}.{_SUMS}", "w") as f:
            json.dump(sums, f)

    def finish(self) -> None:
        """Mark the store complete, listing its chunks in order."""
        self._manifest(complete=True, chunks=[self._stem(*c) for c in self.chunks])


class Trajectories:
    """Lazy reader of a directory written by a sweep with `save_trajectories=`.

    **Fields:** `ts` (n_t,) save times, s; `n`: number of samples of the sweep;
    `manifest`: the whole manifest. Nothing is read until asked for; arrays are
    memory-mapped (`np.load(mmap_mode="r")`). A chunk's files are checked against their
    SHA-256s the first time the chunk is used (one read of the chunk); a mismatch is a
    `ValueError` naming the file.
    """

    def __init__(self, path):
        self.dir = Path(path)
        try:
            self.manifest = json.loads((self.dir / _MANIFEST).read_text())
        except (OSError, ValueError) as e:
            raise ValueError(f"{str(self.dir)!r} holds no saved trajectories "
                             f"({_MANIFEST}: {e})") from None
        self._check_manifest()
        if not self.manifest.get("complete"):
            raise ValueError(f"{str(self.dir)!r}: the sweep writing these trajectories has "
                             "not finished; rerun it (with a checkpoint only the missing "
                             "chunks are computed)")
        self.ts = np.asarray(self.manifest["ts"])
        self.n = int(self.manifest["n"])
        self._plan = plan_digest(self.manifest["plan"])
        self._checked: set[str] = set()  # chunks whose files passed their checksums
        self._index = None

    def _check_manifest(self) -> None:
        """`ValueError` for a manifest of another format, or edited or damaged."""
        doc = self.manifest if isinstance(self.manifest, dict) else {}
        if doc.get("format") in _OLDER:
            raise ValueError(f"{str(self.dir)!r} was written by an older crank-jax, "
                             "without checksums on all it holds; rerun the sweep into a new "
                             "directory")
        if doc.get("format") != _FORMAT:
            raise ValueError(f"{str(self.dir)!r}: {_MANIFEST} is not a crank-jax "
                             "trajectory manifest")
        if doc.get("sha256") != _manifest_digest(doc):
            raise ValueError(f"saved trajectories {str(self.dir / _MANIFEST)!r} are damaged "
                             "or were edited (checksum mismatch: its times, sample count or "
                             "chunk list are not the sweep's); rerun the sweep")

    def _check(self, stem: str) -> None:
        """A chunk's files against their checksums, once (`ValueError` naming a bad one)."""
        if stem not in self._checked:
            _check_chunk(self.dir, self._plan, stem)
            self._checked.add(stem)

    def chunks(self) -> Iterator[tuple[np.ndarray, dict[str, np.ndarray]]]:
        """Yield `(idx, {"phi": (m, n_t), "dphi": (m, n_t)})` per chunk, memory-mapped;
        `idx` (m,): the rows' sample indices."""
        for stem in self.manifest["chunks"]:
            self._check(stem)
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
                _check_chunk(self.dir, self._plan, stem, keys=("idx",))
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
            stem = self.manifest["chunks"][c]
            self._check(stem)
            base = self.dir / stem
            for k in FIELDS:
                out[k][rows] = np.load(f"{base}.{k}.npy", mmap_mode="r")[where[rows, 1]]
        return {k: v.reshape(*want.shape, self.ts.size) for k, v in out.items()}


def load_trajectories(path: str | os.PathLike) -> Trajectories:
    """Open the trajectories a sweep saved in `path` (`save_trajectories=`), lazily:
    see [`Trajectories`][]."""
    return Trajectories(path)
