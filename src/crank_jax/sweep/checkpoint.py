"""Resumable sweeps: each finished chunk is written to a checkpoint directory, and a rerun
of the same plan computes only the chunks that are missing.

The directory holds `manifest.json` (the plan: scene, samples, seed, outputs, save times,
solver, step budget, chunk size, sorting, crank-jax's version) and one `chunk-B-S.npz` per
finished chunk (block start `B`, start `S` within the block's sorted order), each written
atomically with a SHA-256 of its arrays and of the plan inside (a chunk of another plan,
e.g. left in a directory whose manifest was deleted, fails it). The plan is compared
exactly: numbers at full precision, arrays by digest. A rerun whose plan differs from the
manifest is refused, naming what differs; a chunk file that cannot be read or whose
checksum does not match is computed again. A chunk's samples are fixed by the plan (the
samples depend on the seed only, the sorting on the samples, the chunks on the chunk size),
so resumed and uninterrupted runs give identical results.

In a multi-process run ([`SharedCheckpoint`][]) process 0 alone reads and writes the
directory (it holds every chunk's gathered results; the others need not see the
directory at all) and, per chunk, tells the others whether the chunk is saved and sends
them its arrays. So the resumed run may use another number of processes, as long as the
device count (and so the rounded chunk size, which the manifest holds) is the same.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from pathlib import Path

import jax
import numpy as np

from ..runtime.io import atomic_write, make_dir
from .collective import broadcast, on_process_0

__all__ = ["Checkpoint", "SharedCheckpoint", "plan_manifest", "plan_digest"]

_MANIFEST = "manifest.json"


def _digest(arrays: dict[str, np.ndarray], plan: str = "") -> str:
    """SHA-256 of `arrays` (names, dtypes, shapes, bytes), bound to the digest `plan` of
    the plan they belong to (so that a chunk of another plan never passes for one of
    this plan's, even without a manifest)."""
    h = hashlib.sha256(plan.encode())
    for k in sorted(arrays):
        a = np.ascontiguousarray(arrays[k])
        h.update(f"{k}:{a.dtype.str}:{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _version() -> str:
    # The installed distribution's version (the package's own `__init__` would be an
    # import cycle).
    from importlib import metadata

    try:
        return metadata.version("crank-jax")
    except metadata.PackageNotFoundError:
        return "unknown"


def _exact(dist) -> str:
    """A distribution's text at full precision (`repr` of each float): `str` prints `%g`,
    which made `normal(2, 0.1)` and `normal(2.0000004, 0.1)` the same plan."""
    fields = ",".join(f"{f.name}={float(getattr(dist, f.name))!r}"
                      for f in dataclasses.fields(dist))
    return f"{type(dist).__name__}({fields})"


def plan_digest(manifest: dict) -> str:
    """SHA-256 of a plan's manifest ([`plan_manifest`][]): exact values throughout."""
    return hashlib.sha256(json.dumps(manifest, sort_keys=True).encode()).hexdigest()


def plan_manifest(plan, chunk: int, max_steps: int) -> dict:
    """What decides a sweep's chunks, exactly (numbers at full precision, arrays by
    their SHA-256)."""
    spec = plan.spec
    samples = {k: _exact(v) for k, v in spec.dists.items()}
    samples.update({k: "array sha256 " + _digest({"a": np.asarray(v)})
                    for k, v in spec.arrays.items()})
    leaves, treedef = jax.tree.flatten(plan.scene)
    scene = _digest({f"{i:04d}": np.asarray(x) for i, x in enumerate(leaves)}
                    | {"tree": np.frombuffer(str(treedef).encode(), np.uint8)})
    return {"crank_jax_version": _version(), "scene": scene,
            "samples": samples, "n": int(plan.n), "seed": int(plan.seed),
            "outputs": list(plan.reductions),
            "save_times": _digest({"ts": np.asarray(plan.ts)}), "solver": plan.solver,
            "max_steps": int(max_steps), "chunk_size": int(chunk), "sort": bool(plan.sort)}


class Checkpoint:
    """A checkpoint directory for one plan (see the module docstring). `writer`: whether
    this process writes (process 0 of a multi-process run)."""

    def __init__(self, path, plan, chunk: int, max_steps: int, writer: bool = True):
        self.dir = Path(path)
        self.writer = writer
        #: Also needed for a saved chunk to count, `require(b0, start, idx) -> bool` (its
        #: saved trajectories, see `sweep(save_trajectories=)`).
        self.require = None
        if self.dir.exists() and not self.dir.is_dir():
            raise ValueError(f"checkpoint {str(self.dir)!r} is a file, not a directory; "
                             "give a directory (it is created if missing)")
        make_dir(self.dir, "checkpoint")
        if writer and not os.access(self.dir, os.W_OK | os.X_OK):
            raise ValueError(f"checkpoint {str(self.dir)!r} is not writable; give a "
                             "directory you may write to")
        want = plan_manifest(plan, chunk, max_steps)
        self.plan = plan_digest(want)
        path = self.dir / _MANIFEST
        if path.exists():
            try:
                have = json.loads(path.read_text())
            except (OSError, ValueError):
                have = None
            if not isinstance(have, dict):
                raise ValueError(f"checkpoint {str(self.dir)!r}: {_MANIFEST} is unreadable; "
                                 "delete the directory or give another one")
            differ = [k for k in want if have.get(k) != want[k]]
            if differ:
                raise ValueError(f"checkpoint {str(self.dir)!r} holds another sweep: its "
                                 f"{', '.join(differ)} differ from this one's; give another "
                                 "directory, or delete it to start again")
        elif writer:
            with atomic_write(path, "w") as f:
                json.dump(want, f, indent=1)

    def _file(self, b0: int, start: int) -> Path:
        return self.dir / f"chunk-{b0}-{start}.npz"

    def load(self, b0: int, start: int, idx: np.ndarray):
        """The chunk's saved `(res, st, ns, solver_index)`, or `None` when it is missing,
        unreadable, damaged, or of other samples (it is then computed again)."""
        path = self._file(b0, start)
        if not path.exists():
            return None
        try:
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files if k != "sha256"}
                ok = str(z["sha256"]) == _digest(arrays, self.plan)
        except Exception:  # noqa: BLE001 (any damage: BadZipFile, zlib, pickle refusal...)
            return None  # computed again
        if not ok or not np.array_equal(arrays.get("idx"), idx):
            return None
        if self.require is not None and not self.require(b0, start, idx):
            return None
        res = {k[4:]: v for k, v in arrays.items() if k.startswith("out.")}
        return res, arrays["status"], arrays["steps"], int(arrays["solver"])

    def save(self, b0: int, start: int, idx, res, st, ns, solver_index: int) -> None:
        if not self.writer:
            return
        arrays = {"idx": np.asarray(idx), "status": np.asarray(st), "steps": np.asarray(ns),
                  "solver": np.asarray(solver_index)}
        arrays.update({f"out.{k}": np.asarray(v) for k, v in res.items()})
        with atomic_write(self._file(b0, start), "wb") as f:
            np.savez(f, sha256=np.asarray(_digest(arrays, self.plan)), **arrays)


class SharedCheckpoint:
    """The checkpoint of a multi-process run (see the module docstring): the same
    `load`/`save` as [`Checkpoint`][], called by every process at the same chunks."""

    def __init__(self, path, plan, chunk: int, max_steps: int):
        self.inner = on_process_0(lambda: Checkpoint(path, plan, chunk, max_steps),
                                  f"checkpoint {str(path)!r}")
        self.n_t = int(np.shape(plan.ts)[0])
        self.outputs = tuple(plan.reductions)

    def _canonical(self, got, m: int):
        from .reductions import TRAJECTORY_OUTPUTS

        if got is None:
            got = ({k: np.zeros((m, self.n_t) if k in TRAJECTORY_OUTPUTS else m)
                    for k in self.outputs}, np.zeros(m), np.zeros(m), 0)
        res, st, ns, si = got
        return {"res": {k: np.asarray(res[k], np.float64) for k in self.outputs},
                "st": np.asarray(st, np.int8), "ns": np.asarray(ns, np.int64),
                "si": np.asarray([si], np.int64)}

    @property
    def require(self):
        return None if self.inner is None else self.inner.require

    @require.setter
    def require(self, fn) -> None:
        if self.inner is not None:
            self.inner.require = fn

    def load(self, b0: int, start: int, idx: np.ndarray):
        got = self.inner.load(b0, start, idx) if self.inner is not None else None
        if not broadcast(np.array([got is not None], np.int8))[0]:
            return None
        t = broadcast(self._canonical(got, idx.size))
        return t["res"], t["st"], t["ns"], int(t["si"][0])

    def save(self, b0: int, start: int, idx, res, st, ns, solver_index: int) -> None:
        if self.inner is not None:
            self.inner.save(b0, start, idx, res, st, ns, solver_index)
