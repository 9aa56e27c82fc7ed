"""`track_stream`: follow a long record straight from its file, chunk by chunk, in bounded
memory: the file is read `CHUNK` rows at a time
([`RecordChunks`][crank_jax.records.chunked.RecordChunks]), the filter runs on each chunk
as it comes, the result keeps every `every`-th sample (the change test still sees every
sample), and the full-resolution path can be written to a CSV file as it goes (atomically:
the file appears, whole, when the record is done)."""

from __future__ import annotations

import contextlib
import itertools
import math
import os
from collections.abc import Sequence

import numpy as np

from ..records.chunked import RecordChunks
from ..records.data import Data
from ..records.sensors import select_sensors
from ..records.table import DataError, header_columns
from ..runtime.io import atomic_write
from ..scene import Scene
from . import runner
from .ekf import Steps
from .tracked import TrackResult
from .tracking import finish, prepare

__all__ = ["track_stream", "path_columns"]


def path_columns(free: Sequence[str]) -> list[str]:
    """The columns of the path file: `t`, `phi`, `dphi`, each free name and its standard
    error (`<name>_se`), the change test's `statistic` and `alarm` (0 or 1)."""
    return (["t", "phi", "dphi"] + [c for n in free for c in (n, f"{n}_se")]
            + ["statistic", "alarm"])


def track_stream(scene: Scene, path: str | os.PathLike, free: Sequence[str] = ("k", "c"),
                 *, channels: Sequence[str] | None = None, t_col: str = "t", every: int = 1,
                 path_out: str | os.PathLike | None = None, path_every: int = 1,
                 start: str = "batch", start_seconds: float = 5.0,
                 false_alarm_rate: float = 1.0, change_ratio: float = 4.0,
                 settle: float = 5.0, q_param: float = 1e-4,
                 progress: bool = True) -> TrackResult:
    """[`track`][crank_jax.online.tracking.track] a record read from `path` chunk by chunk.

    `path`: a text table (a header line, then `t_col` and the channels' columns) or a
    `.npy` array (n, 1 + C) of `t` and the channels in order. `channels`: the channel
    texts (as the CLI's `--channel`: `x_s`, `phi:angle_deg:deg`, ...; default: the
    scene's sensors found in the header, else `phi`). The loads are the scene's (a
    measured `P`/`tau` column needs [`track`][crank_jax.online.tracking.track]). The
    filter starts from the record's first `start_seconds` (at least one chunk), read
    once and kept only until filtered; its step size and noise levels are set from them.
    `every`: keep every `every`-th sample in the result; `path_out`: write every
    `path_every`-th sample's filtered values to this CSV ([`path_columns`][]).
    Other arguments as [`track`][crank_jax.online.tracking.track]'s.

    Memory: the chunk, the start's samples and the kept path (`n / every` samples),
    whatever the record's length."""
    for name, v in (("every", every), ("path_every", path_every)):
        if not (isinstance(v, int) and v >= 1):
            raise ValueError(f"{name}= must be an integer >= 1, got {v!r}")
    if not (isinstance(settle, (int, float)) and math.isfinite(settle) and settle > 0):
        raise ValueError(f"settle= must be a finite number > 0, got {settle!r}")
    header = None if str(path).endswith(".npy") else header_columns(path)
    sensors = select_sensors(channels, scene.sensors, header)
    reader = RecordChunks(path, [s.column for s in sensors], t_col, rows=runner.CHUNK)
    chunks = iter(reader)
    head = _head(chunks, start_seconds, str(path))
    t_head = np.concatenate([t for t, _ in head])
    y_head = np.concatenate([y for _, y in head])
    data = Data(t_head, channels={s.name: s.to_si(y_head[:, j]) for j, s in enumerate(sensors)},
                sensors=sensors, source=str(path))
    p = prepare(scene, data, free, start=start, start_seconds=start_seconds,
                false_alarm_rate=false_alarm_rate, change_ratio=change_ratio,
                q_param=q_param, progress=progress)
    factors = np.array([s.factor for s in sensors])
    del data, t_head, y_head
    # The samples in SI, the start's chunks first (dropped as they are filtered).
    todo = ((t, y * factors) for t, y in itertools.chain(_drain(head), chunks))
    with _path_file(path_out, p.free, p.log, path_every) as sink:
        run = runner.run_chunks(p.model, p.settings, p.state, todo, every, progress,
                                total=None, sink=sink)
    return finish(p, run, settle, every, stream={
        "path": str(path), "samples": run.n, "start_samples": int(p.ts.shape[0]),
        "path_out": None if path_out is None else str(path_out), "path_every": path_every})


def _head(chunks, seconds: float, where: str) -> list:
    """The first chunks of `chunks`, until they span `seconds` s (or the record ends)."""
    head = []
    for t, y in chunks:
        head.append((t, y))
        if t[-1] - head[0][0][0] >= seconds:
            break
    if not head:
        raise DataError(f"{where}: the record has no samples (a header and no data)")
    return head


def _drain(items: list):
    """`items` one by one, each dropped from the list as it is handed out."""
    while items:
        yield items.pop(0)


@contextlib.contextmanager
def _path_file(path_out, free, log, every: int):
    """A sink writing the filtered path to `path_out` (atomically), or None."""
    if path_out is None:
        yield None
        return
    with atomic_write(path_out) as f:
        f.write(",".join(path_columns(free)) + "\n")
        state = {"lo": 0}

        def sink(t: np.ndarray, steps: Steps) -> None:
            lo = state["lo"]
            first = (-lo) % every
            z, sz = steps.x[first::every, 2:], steps.se[first::every, 2:]
            cols = [t[first::every], steps.x[first::every, 0], steps.x[first::every, 1]]
            for j in range(z.shape[1]):
                v = np.exp(z[:, j]) if log[j] else z[:, j]
                cols += [v, v * sz[:, j] if log[j] else sz[:, j]]
            cols += [steps.g[first::every], steps.alarm[first::every].astype(float)]
            np.savetxt(f, np.stack(cols, axis=1), fmt="%.12g", delimiter=",")
            state["lo"] = lo + t.shape[0]

        yield sink
