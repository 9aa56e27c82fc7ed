"""The result of a Monte Carlo sweep and its per-sample status codes."""

from __future__ import annotations

import equinox as eqx
import numpy as np

from ..model.dynamics import Structure
from ..runtime.io import atomic_write
from ..solve.policy import SOLVERS

__all__ = ["SweepResult", "STATUS", "OK", "INVALID", "MAX_STEPS", "FAILED", "NONFINITE"]

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
