"""The result of a Monte Carlo sweep and its per-sample status codes."""

from __future__ import annotations

import equinox as eqx
import numpy as np

from ..model.dynamics import Structure
from ..runtime.io import atomic_write
from ..runtime.progress import progress_bar
from ..solve.policy import SOLVERS
from .reductions import TRAJECTORY_OUTPUTS

__all__ = ["SweepResult", "Filling", "STATUS", "OK", "INVALID", "MAX_STEPS", "FAILED", "NONFINITE"]

#: Per-sample status codes: `SweepResult.status == i` means `STATUS[i]`.
STATUS: tuple[str, ...] = ("ok", "invalid", "max_steps", "failed", "nonfinite")
OK, INVALID, MAX_STEPS, FAILED, NONFINITE = range(len(STATUS))


class SweepResult(eqx.Module):
    """The result of a [`sweep`][], in the original sample order (host NumPy arrays).

    **Fields:**

    - `samples`: varied name -> (n,) values drawn (before invalid ones were set aside).
    - `outputs`: reduction name -> (n,) values, or (n, n_t) for `"phi"`/`"dphi"`. Samples
      whose status is not `"ok"` hold 0 here (never NaN): mask with `ok`.
    - `status`: (n,) int8 codes into [`STATUS`][].
    - `num_steps`: (n,) solver steps (accepted + rejected); 0 for invalid samples.
    - `solver`: (n,) int8 index into `SOLVERS` of the solver each sample ran with.
    - `ts`: (n_t,) save times, s. `structure`: the static structure compiled.
    - `seed`: the seed the samples were drawn with (-1 for explicit arrays only).
    """

    samples: dict[str, np.ndarray]
    outputs: dict[str, np.ndarray]
    status: np.ndarray
    num_steps: np.ndarray
    solver: np.ndarray
    ts: np.ndarray
    structure: Structure = eqx.field(static=True)
    seed: int = eqx.field(static=True, default=0)

    @property
    def n(self) -> int:
        """Number of samples."""
        return int(self.status.shape[0])

    @property
    def ok(self) -> np.ndarray:
        """(n,) True where the sample's solve succeeded."""
        return self.status == OK

    def counts(self) -> dict[str, int]:
        """Number of samples per status name."""
        return {name: int(np.sum(self.status == i)) for i, name in enumerate(STATUS)}

    def summary(self) -> dict[str, dict[str, float]]:
        """Statistics of every scalar output over the successful samples:
        mean, std, min, p05, p50, p95, max (NaN-free: an empty set gives no entry)."""
        out = {}
        ok = self.ok
        for name, v in self.outputs.items():
            if v.ndim != 1 or not ok.any():
                continue
            x = v[ok]
            q = np.percentile(x, [5, 50, 95])
            out[name] = dict(mean=float(x.mean()), std=float(x.std()), min=float(x.min()),
                             p05=float(q[0]), p50=float(q[1]), p95=float(q[2]),
                             max=float(x.max()))
        return out

    def save(self, path) -> None:
        """Write an `.npz` file atomically: `sample.<name>`, `output.<name>`, `status`,
        `status_names`, `num_steps`, `solver`, `solver_names`, `ts`, `seed`."""
        arrays = {f"sample.{k}": v for k, v in self.samples.items()}
        arrays.update({f"output.{k}": v for k, v in self.outputs.items()})
        arrays.update(status=self.status, status_names=np.array(STATUS),
                      num_steps=self.num_steps, solver=self.solver,
                      solver_names=np.array(SOLVERS), ts=self.ts, seed=np.int64(self.seed))
        with atomic_write(path, "wb") as f:
            np.savez(f, **arrays)


class Filling:
    """A [`SweepResult`][] being filled chunk by chunk, in the original sample order, and
    the sweep's progress (a tqdm bar on stderr with `progress`; `callback(done, total)`
    per chunk)."""

    def __init__(self, plan, progress: bool, callback):
        self.plan = plan
        n, n_t = plan.n, plan.ts.shape[0]
        self.out = {k: np.zeros((n, n_t) if k in TRAJECTORY_OUTPUTS else n)
                    for k in plan.reductions}
        self.values = {k: np.empty(n) for k in plan.spec.names}
        self.status = np.full(n, INVALID, np.int8)
        self.steps = np.zeros(n, np.int64)
        self.solver_used = np.full(n, -1, np.int8)
        self.n, self.done, self.callback, self.bar = n, 0, callback, None
        if progress:
            self.bar = progress_bar(n, "sweep", True, unit="sample", leave=True)

    def drawn(self, b0: int, b1: int, drawn: dict, invalid: np.ndarray) -> None:
        """Samples `b0:b1`'s drawn values; the invalid ones count as done."""
        for k, v in drawn.items():
            self.values[k][b0:b1] = v
        self._advance(int(invalid.sum()))

    def sink(self, b0: int):
        """What the sweep hands each solved chunk of the block starting at `b0` to:
        `sink(idx, res, st, ns, solver_index)`, the chunk's sample indices within the
        block, outputs, status codes, step counts and solver index."""
        def sink(idx, res, st, ns, solver_index):
            i = b0 + idx
            for k, v in res.items():
                self.out[k][i] = v
            self.status[i], self.steps[i], self.solver_used[i] = st, ns, solver_index
            self._advance(idx.size)
            if self.callback is not None:
                self.callback(self.done, self.n)
        return sink

    def _advance(self, k: int) -> None:
        self.done += k
        if self.bar is not None:
            self.bar.update(k)

    def close(self) -> None:
        """Closes the progress bar."""
        if self.bar is not None:
            self.bar.close()

    def result(self) -> SweepResult:
        """The filled result."""
        plan = self.plan
        return SweepResult(self.values, self.out, self.status, self.steps, self.solver_used,
                           plan.ts, plan.structure, plan.seed if plan.random else -1)
