"""Monte Carlo sweeps: many simulations of one scene with varied values, `jax.vmap`-ed,
chunked, bucketed by stiffness, reduced on the fly, sharded over every device.

How a sweep runs:

1. Samples are drawn on the host ([`draw`][]), one seeded stream per field.
2. Invalid samples (e.g. `L <= r`, a negative mass, a NaN) are marked `"invalid"` and
   never reach the solver, so one bad sample cannot raise inside a batch.
3. The static structure is the union of the nominal scene's and every sample's: a field
   varied away from zero switches its term on; nothing else is compiled.
4. Samples are sorted by their linearised fastest rate `|lambda_fast|` (which sets an
   adaptive solver's step count), then cut into fixed-size chunks. A `vmap`-ed solve runs
   in lockstep, so a chunk costs its slowest member's steps: sorting keeps one stiff
   sample from slowing every chunk, and [`choose_solver`][] picks per chunk.
5. Each chunk is one compiled call (no recompilation: the last chunk is padded), sharded
   over a 1-D mesh of all devices along the batch axis. Only the requested reductions
   leave the device; full trajectories only when `"phi"`/`"dphi"` are asked for.
6. Results are scattered back into the original sample order.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Mapping, Sequence

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ..io import atomic_write
from ..model.dynamics import Structure, energy
from ..model.linear import linearize
from ..model.loads import AbstractLoad, ConstantLoad, HarmonicLoad, NoLoad, SampledLoad
from ..model.params import FIELDS, SliderCrank, validation_rules
from ..solve.policy import SOLVERS, choose_solver, fastest_mode
from ..solve.simulate import simulate
from .distributions import AbstractDistribution, draw, parse_distribution

__all__ = ["sweep", "SweepResult", "REDUCTIONS", "STATUS", "VARIABLES",
           "initialize_distributed", "sweep_cost"]

#: Per-sample status codes: `SweepResult.status == i` means `STATUS[i]`.
STATUS: tuple[str, ...] = ("ok", "invalid", "max_steps", "failed", "nonfinite")
_OK, _INVALID, _MAX_STEPS, _FAILED, _NONFINITE = range(len(STATUS))

_LOAD_KEYS = {"load": ("P0", "P1", "P_freq_hz", "P_phase"),
              "torque": ("tau0", "tau1", "tau_freq_hz", "tau_phase")}

#: Names a sweep can vary: the mechanism's fields, the initial state and the loads'
#: mean, amplitude, frequency (Hz) and phase (rad).
VARIABLES: tuple[str, ...] = FIELDS + ("phi0", "dphi0") + _LOAD_KEYS["load"] + _LOAD_KEYS["torque"]

#: Reductions a sweep can compute, name -> description (units). Each is one number per
#: sample, except `"phi"` and `"dphi"`, which store the whole (n_t,) trajectory.
REDUCTIONS: dict[str, str] = {
    "peak_phi": "max |phi| over the saved times, rad",
    "peak_dphi": "max |dphi|, rad/s",
    "final_phi": "phi at t1, rad",
    "final_dphi": "dphi at t1, rad/s",
    "final_energy": "mechanical energy T + V at t1, J",
    "peak_O": "max |O|, the crank-bearing reaction force, N",
    "dominant_freq": "frequency of the largest peak of |FFT(phi - mean)|, Hz",
    "settling_time": "last time |phi - phi(t1)| exceeds 2% of its maximum, s",
    "phi": "the whole crank angle trajectory, rad (n_t values per sample)",
    "dphi": "the whole crank rate trajectory, rad/s (n_t values per sample)",
}
DEFAULT_OUTPUTS = ("peak_phi", "peak_dphi", "final_energy")


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
        return self.status == _OK

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


# ---------------------------------------------------------------------------------------
# Distribution over devices and hosts

_distributed_ready = False


def initialize_distributed(**kwargs) -> None:
    """Join a multi-host run: `jax.distributed.initialize(**kwargs)`, once.

    Call it before any other JAX call. Without arguments JAX reads the cluster from the
    environment (`JAX_COORDINATOR_ADDRESS`, `JAX_NUM_PROCESSES`, `JAX_PROCESS_ID`, or
    SLURM/MPI/cloud auto-detection). Afterwards `jax.devices()` lists every host's devices
    and a [`sweep`][] shards its chunks across all of them; every host draws the same
    samples from the seed and gets the whole result.
    """
    global _distributed_ready
    if not _distributed_ready:
        jax.distributed.initialize(**kwargs)
        _distributed_ready = True


def _to_global(x: np.ndarray, sharding) -> Array:
    # Every process holds the same host array (the samples come from the seed), so each
    # fills in the shards it owns; the same call works with one process.
    return jax.make_array_from_callback(x.shape, sharding, lambda idx: x[idx])


def _to_host(x: Array) -> np.ndarray:
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        return np.asarray(multihost_utils.process_allgather(x, tiled=True))
    return np.asarray(x)


# ---------------------------------------------------------------------------------------
# Building the batch


def _nominal_load_values(load: AbstractLoad) -> tuple[float, float, float, float]:
    if isinstance(load, NoLoad):
        return 0.0, 0.0, 0.0, 0.0
    if isinstance(load, ConstantLoad):
        return float(load.value), 0.0, 0.0, 0.0
    if isinstance(load, HarmonicLoad):
        return tuple(float(x) for x in (load.X0, load.X1, load.freq_hz, load.phase))
    raise TypeError(type(load).__name__)


def _nonzero(v) -> bool:
    if isinstance(v, AbstractDistribution):
        return v.may_be_nonzero()
    return bool(np.any(np.asarray(v) != 0))


def _load_kind(which: str, nominal: AbstractLoad, spec: Mapping) -> str:
    """"fixed" (not varied, e.g. sampled data), "none", "constant" or "harmonic"."""
    keys = _LOAD_KEYS[which]
    varied = [k for k in keys if k in spec]
    if isinstance(nominal, SampledLoad) or (not varied and not isinstance(nominal, NoLoad)):
        if varied:
            raise ValueError(f"the scene's {which} is sampled data; its {varied} cannot be "
                             "varied")
        return "fixed"
    X0, X1, _, _ = _nominal_load_values(nominal)
    amp = X1 != 0 or (keys[1] in spec and _nonzero(spec[keys[1]]))
    mean = X0 != 0 or (keys[0] in spec and _nonzero(spec[keys[0]]))
    if isinstance(nominal, HarmonicLoad) or amp:
        return "harmonic"
    return "constant" if mean else "none"


def _make_load(kind: str, nominal: AbstractLoad, cols: dict[str, np.ndarray]):
    if kind == "fixed":
        return nominal
    if kind == "none":
        return NoLoad()
    if kind == "constant":
        return ConstantLoad(cols["X0"])
    return HarmonicLoad(cols["X0"], cols["X1"], cols["freq"], cols["phase"])


def _columns(scene, values: dict[str, np.ndarray], n: int) -> dict[str, np.ndarray]:
    """Every batched number of the scene, as (n,) float64: nominal or sampled."""
    cols = {f: np.full(n, float(np.asarray(getattr(scene.mech, f)))) for f in FIELDS}
    cols["phi0"] = np.full(n, float(np.asarray(scene.phi0)))
    cols["dphi0"] = np.full(n, float(np.asarray(scene.dphi0)))
    for which in ("load", "torque"):
        nominal = getattr(scene, which)
        base = (0.0,) * 4 if isinstance(nominal, SampledLoad) else _nominal_load_values(nominal)
        for key, b in zip(_LOAD_KEYS[which], base):
            cols[key] = np.full(n, b)
    for name, v in values.items():
        cols[name] = np.array(v, dtype=np.float64)
    return cols


def _invalid(cols: dict[str, np.ndarray]) -> np.ndarray:
    bad = np.zeros(next(iter(cols.values())).shape, bool)
    with np.errstate(invalid="ignore"):
        for _, mask, _ in validation_rules({f: cols[f] for f in FIELDS}):
            bad |= mask
        for name in VARIABLES[len(FIELDS):]:
            bad |= ~np.isfinite(cols[name])
        bad |= (cols["P_freq_hz"] < 0) | (cols["tau_freq_hz"] < 0)
    return bad


def _take(cols: dict[str, np.ndarray], idx) -> dict[str, np.ndarray]:
    return {k: v[idx] for k, v in cols.items()}


def _build(scene, cols: dict[str, np.ndarray], kinds: dict[str, str]):
    mech = SliderCrank(**{f: cols[f] for f in FIELDS})
    loads = []
    for which in ("load", "torque"):
        keys = _LOAD_KEYS[which]
        sub = dict(zip(("X0", "X1", "freq", "phase"), (cols[k] for k in keys)))
        loads.append(_make_load(kinds[which], getattr(scene, which), sub))
    return mech, loads[0], loads[1], cols["phi0"], cols["dphi0"]


# ---------------------------------------------------------------------------------------
# The compiled chunk


def _settling_time(ts, phi):
    dev = jnp.abs(phi - phi[-1])
    band = 0.02 * jnp.max(dev)
    outside = dev > band
    # The last index outside the band; the settling time is the next save time.
    last = jnp.max(jnp.where(outside, jnp.arange(ts.shape[0]), -1))
    return jnp.where(last < 0, ts[0], ts[jnp.minimum(last + 1, ts.shape[0] - 1)])


def _dominant_freq(ts, phi):
    n = ts.shape[0]
    dt = (ts[-1] - ts[0]) / (n - 1)
    spec = jnp.abs(jnp.fft.rfft(phi - jnp.mean(phi)))
    m = spec.shape[0]
    k = jnp.clip(1 + jnp.argmax(spec[1:]), 1, m - 2)
    # Quadratic interpolation of log|FFT| over the peak and its neighbours: the bins are
    # 1/t1 apart, far coarser than the frequency differences a sweep looks for.
    a, b, c = (jnp.log(spec[i] + 1e-300) for i in (k - 1, k, k + 1))
    den = a - 2 * b + c
    shift = jnp.where(den < 0, 0.5 * (a - c) / jnp.where(den < 0, den, -1.0), 0.0)
    return (k + jnp.clip(shift, -0.5, 0.5)) / (n * dt)


def _reduce(name, traj, mech) -> Array:
    phi, dphi, ts = traj.phi, traj.dphi, traj.ts
    if name == "peak_phi":
        return jnp.max(jnp.abs(phi))
    if name == "peak_dphi":
        return jnp.max(jnp.abs(dphi))
    if name == "final_phi":
        return phi[-1]
    if name == "final_dphi":
        return dphi[-1]
    if name == "final_energy":
        return energy(mech, phi[-1], dphi[-1])
    if name == "peak_O":
        return jnp.max(jnp.hypot(traj.extras["O_x"], traj.extras["O_y"]))
    if name == "dominant_freq":
        return _dominant_freq(ts, phi)
    if name == "settling_time":
        return _settling_time(ts, phi)
    if name == "phi":
        return phi
    if name == "dphi":
        return dphi
    raise AssertionError(name)


@eqx.filter_jit
def _run_chunk(mech, load, torque, phi0, dphi0, ts, rtol, atol, *, load_fixed, torque_fixed,
               solver, structure, reductions, max_steps):
    extras = ("reactions",) if "peak_O" in reductions else ()

    def one(mech, load, torque, phi0, dphi0):
        traj = simulate(mech, phi0, dphi0, ts, load=load, torque=torque, solver=solver,
                        rtol=rtol, atol=atol, max_steps=max_steps, outputs=extras,
                        structure=structure, throw=False)
        out = {name: _reduce(name, traj, mech) for name in reductions}
        ok = traj.result == diffrax.RESULTS.successful
        finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(v)) for v in out.values()])) \
            if out else jnp.array(True)
        status = jnp.where(
            ~ok,
            jnp.where(traj.result == diffrax.RESULTS.max_steps_reached, _MAX_STEPS, _FAILED),
            jnp.where(finite, _OK, _NONFINITE)).astype(jnp.int8)
        # Never hand out NaN or inf: a sample that did not finish reads 0, and its status
        # says why.
        out = {k: jnp.where(status == _OK, v, 0.0) for k, v in out.items()}
        return out, status, traj.num_steps

    axes = (0, None if load_fixed else 0, None if torque_fixed else 0, 0, 0)
    return jax.vmap(one, in_axes=axes)(mech, load, torque, phi0, dphi0)


class _Plan(eqx.Module):
    values: dict
    cols: dict
    invalid: np.ndarray
    kinds: dict
    structure: Structure
    reductions: tuple
    order: np.ndarray
    ts: np.ndarray
    n: int
    span: float
    rtol: float
    atol: float
    solver: str
    seed: int


def _prepare(scene, samples, outputs, n, seed, t1, num_saves, solver, chunk_size, sort):
    reductions = tuple(dict.fromkeys(outputs))
    for name in reductions:
        if name not in REDUCTIONS:
            raise ValueError(f"unknown sweep output {name!r}; choose from {list(REDUCTIONS)}")
    for name in samples:
        if name not in VARIABLES:
            raise ValueError(f"cannot vary {name!r}; choose from {list(VARIABLES)}")
    if chunk_size < 1:
        raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
    solver = scene.solver if solver is None else solver
    if solver not in SOLVERS:
        raise ValueError(f"unknown solver {solver!r}; choose from {list(SOLVERS)}")
    spec = {k: parse_distribution(v) if isinstance(v, str) else v for k, v in samples.items()}
    values = draw(spec, n, seed)
    n = len(next(iter(values.values()))) if values else int(n or 1)
    seed = seed if any(isinstance(v, AbstractDistribution) for v in spec.values()) else -1

    cols = _columns(scene, values, n)
    invalid = _invalid(cols)
    # Set invalid samples aside on the nominal values: validated inside jit, one of them
    # would raise for the whole chunk.
    nominal = _columns(scene, {}, n)
    for k in cols:
        cols[k] = np.where(invalid, nominal[k], cols[k])
    kinds = {w: _load_kind(w, getattr(scene, w), spec) for w in ("load", "torque")}
    structure = Structure.of(scene.mech).union(
        Structure.of(SliderCrank(**{f: cols[f] for f in FIELDS})))

    ts = np.linspace(0.0, scene.t1 if t1 is None else float(t1),
                     scene.samples if num_saves is None else int(num_saves))
    if not (ts[-1] > 0 and ts.shape[0] >= 2):
        raise ValueError("a sweep needs t1 > 0 and at least 2 save times")
    span = float(ts[-1] - ts[0])
    rtol = float(np.asarray(scene.rtol))
    atol = float(np.asarray(scene.atol))

    valid_idx = np.flatnonzero(~invalid)
    if sort and valid_idx.size:
        lin_mech, lin_load, _, _, _ = _build(scene, _take(cols, valid_idx), kinds)
        lam, _ = fastest_mode(linearize(lin_mech, lin_load if kinds["load"] != "fixed"
                                        else getattr(scene, "load")))
        valid_idx = valid_idx[np.argsort(np.asarray(lam), kind="stable")]

    return _Plan(values, cols, invalid, kinds, structure, reductions, valid_idx, ts, n, span,
                 rtol, atol, solver, seed)


# ---------------------------------------------------------------------------------------
# The public function


def sweep(
    scene,
    samples: Mapping[str, AbstractDistribution | str | float | np.ndarray],
    outputs: Sequence[str] = DEFAULT_OUTPUTS,
    *,
    n: int | None = None,
    seed: int = 0,
    t1: float | None = None,
    num_saves: int | None = None,
    solver: str | None = None,
    max_steps: int = 100_000,
    chunk_size: int = 1024,
    sort: bool = True,
    devices: Sequence[jax.Device] | None = None,
    progress: bool = False,
    callback: Callable[[int, int], None] | None = None,
) -> SweepResult:
    """Simulate a [`Scene`][] for many sampled values at once.

    **Arguments:**

    - `scene`: the nominal scene; fields not in `samples` keep its values.
    - `samples`: name (see [`VARIABLES`][]) -> a distribution (e.g. `Normal(2.0, 0.1)` or
      `"normal(2.0,0.1)"`), a number, or an explicit (n,) array.
    - `outputs`: reductions to compute (see [`REDUCTIONS`][]); nothing else is computed.
    - `n`: number of samples (optional when `samples` holds arrays). `seed`: integer seed.
    - `t1`, `num_saves`: horizon (s) and number of uniform save times on [0, t1]; default
      the scene's. Peaks and the spectrum are taken over the saved times.
    - `solver`: force one of `SOLVERS`; default the scene's, where `"auto"` is decided per
      chunk by [`choose_solver`][] from the chunk's fastest linearised mode.
    - `max_steps`: step budget per sample; a sample that runs out gets status
      `"max_steps"` and the others are kept.
    - `chunk_size`: samples per compiled call (bounds memory: about
      `chunk_size * num_saves * 16` bytes of trajectory per chunk); rounded up to a
      multiple of the number of devices.
    - `sort`: bucket samples by linearised fastest rate before chunking.
    - `devices`: devices to shard each chunk over (default: all of `jax.devices()`, which
      spans every host after [`initialize_distributed`][]).
    - `progress`: show a tqdm bar on stderr. `callback(done, total)`: called per chunk.

    **Returns:** a [`SweepResult`][] in the original sample order.
    """
    plan = _prepare(scene, samples, outputs, n, seed, t1, num_saves, solver, chunk_size,
                    sort)
    cols, invalid, kinds, structure, reductions = (plan.cols, plan.invalid, plan.kinds,
                                                   plan.structure, plan.reductions)
    values, valid_idx, ts, n, span = plan.values, plan.order, plan.ts, plan.n, plan.span
    rtol, atol, solver = plan.rtol, plan.atol, plan.solver
    devices = list(jax.devices() if devices is None else devices)
    ndev = len(devices)
    chunk = int(math.ceil(min(chunk_size, max(valid_idx.size, 1)) / ndev) * ndev)
    sharding = None
    if ndev > 1:
        mesh = jax.sharding.Mesh(np.array(devices), ("batch",))
        sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("batch"))
        replicated = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())

    n_t = ts.shape[0]
    out = {name: np.zeros((n, n_t) if name in ("phi", "dphi") else n) for name in reductions}
    status = np.full(n, _INVALID, np.int8)
    steps = np.zeros(n, np.int64)
    solver_used = np.full(n, -1, np.int8)

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=n, file=sys.stderr, unit="sample", desc="sweep")
        bar.update(int(invalid.sum()))
    ts_j = jnp.asarray(ts)
    rtol_j, atol_j = jnp.asarray(rtol), jnp.asarray(atol)
    if sharding is not None:
        ts_j, rtol_j, atol_j = (jax.device_put(x, replicated) for x in (ts_j, rtol_j, atol_j))
    done = int(invalid.sum())
    for start in range(0, valid_idx.size, chunk):
        idx = valid_idx[start:start + chunk]
        # Pad the last chunk with its own first sample: one shape, one compilation.
        padded = np.concatenate([idx, np.full(chunk - idx.size, idx[0])])
        sub = _take(cols, padded)
        mech, load, torque, phi0, dphi0 = _build(scene, sub, kinds)
        name = solver
        if name == "auto":
            lin_load = load if kinds["load"] != "fixed" else scene.load
            name = choose_solver(mech, rtol, lin_load, span=span)
        batch = (mech, load, torque, jnp.asarray(phi0), jnp.asarray(dphi0))
        if sharding is not None:
            batch = tuple(
                jax.tree.map(lambda x: _to_global(np.asarray(x), sharding), b)
                if not (i in (1, 2) and kinds[("load", "torque")[i - 1]] == "fixed")
                else jax.device_put(b, replicated)
                for i, b in enumerate(batch))
        res, st, ns = _run_chunk(
            *batch, ts_j, rtol_j, atol_j, load_fixed=kinds["load"] == "fixed",
            torque_fixed=kinds["torque"] == "fixed", solver=name, structure=structure,
            reductions=reductions, max_steps=int(max_steps))
        m = idx.size
        for k in reductions:
            out[k][idx] = _to_host(res[k])[:m]
        status[idx] = _to_host(st)[:m]
        steps[idx] = _to_host(ns)[:m]
        solver_used[idx] = SOLVERS.index(name)
        done += m
        if bar is not None:
            bar.update(m)
        if callback is not None:
            callback(done, n)
    if bar is not None:
        bar.close()
    return SweepResult(values, out, status, steps, solver_used, ts, structure,
                       plan.seed)


def sweep_cost(
    scene,
    samples: Mapping[str, AbstractDistribution | str | float | np.ndarray],
    outputs: Sequence[str] = DEFAULT_OUTPUTS,
    *,
    n: int = 8,
    solver: str = "tsit5",
    num_saves: int | None = None,
    structure: Structure | None = None,
) -> dict[str, float]:
    """What the compiled chunk of a [`sweep`][] costs, from XLA's own cost analysis.

    For showing that unused outputs, bodies and loads cost nothing: compare two scenes
    or two output lists. XLA counts a loop body once, so `flops` is about the work of
    one solver step plus the reductions, not of a whole solve.

    **Arguments:** as for [`sweep`][] (`n` samples in one chunk); `structure` overrides
    the sweep's own (e.g. `Structure()`, every term, to see what skipping saves).

    **Returns:** `flops`, `transcendentals`, `bytes_accessed` and `hlo_lines` (the size of
    the optimised HLO text).
    """
    plan = _prepare(scene, samples, outputs, n, 0, None, num_saves, solver, n, False)
    mech, load, torque, phi0, dphi0 = _build(scene, plan.cols, plan.kinds)
    lowered = _run_chunk.lower(
        mech, load, torque, jnp.asarray(phi0), jnp.asarray(dphi0), jnp.asarray(plan.ts),
        jnp.asarray(plan.rtol), jnp.asarray(plan.atol), load_fixed=plan.kinds["load"] == "fixed",
        torque_fixed=plan.kinds["torque"] == "fixed", solver=plan.solver,
        structure=plan.structure if structure is None else structure,
        reductions=plan.reductions, max_steps=1000)
    compiled = lowered.compile().compiled  # equinox wraps jax.stages.Compiled
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    return {"flops": float(cost.get("flops", 0.0)),
            "transcendentals": float(cost.get("transcendentals", 0.0)),
            "bytes_accessed": float(cost.get("bytes accessed", 0.0)),
            "hlo_lines": float(len(compiled.as_text().splitlines()))}
