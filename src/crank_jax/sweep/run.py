"""Monte Carlo sweeps: many simulations of one scene with varied values, `jax.vmap`-ed,
chunked, bucketed by stiffness, reduced on the fly, sharded over every device.

How a sweep runs ([`make_plan`][] checks everything first):

1. Samples are drawn on the host ([`draw`][]) block by block (`plan.SORT_BLOCK` samples),
   one seeded stream per field and block of `DRAW_BLOCK`: the samples depend on the seed
   only, never on the chunk size, and the working memory is bounded by the block.
2. Invalid samples (e.g. `L <= r`, a negative mass, a NaN) are marked `"invalid"` and
   never reach the solver, so one bad sample cannot raise inside a batch.
3. The static structure is the union of the nominal scene's and every term a varied
   field may switch on; a varied load parameter promotes the scene's load (none ->
   constant -> harmonic) through the load table. Nothing else is compiled.
4. Within a block, samples are sorted by their linearised fastest rate `|lambda_fast|`
   (which sets an adaptive solver's step count), then cut into fixed-size chunks. Each
   member of a `vmap`-ed solve has its own step control, but the batch's loop runs until
   its slowest member is done (the others wait), so a chunk costs its slowest member's
   steps: sorting keeps one stiff sample from slowing every chunk. `"auto"` is decided
   per chunk by the solver policy ([`resolve_solver`][], with `batch_invariant=True`):
   the fused `"dopri8-uniform"` whenever the chunk is not stiff and no load is sampled
   (a sweep's save times are always uniform), whose steps are per member by
   construction: a sweep's samples get exactly their own solve, whatever chunk they
   land in.
5. Each chunk is one compiled program (no recompilation: the last chunk is padded), run
   on every device at once, each on its equal part of the chunk (see `_Devices`). Only
   the requested reductions leave the device; full trajectories only when
   `"phi"`/`"dphi"` are asked for, or to be streamed to disk (`save_trajectories`).
6. Results are written into the original sample order.

Memory: the result holds, per sample, 8 bytes per varied field and per scalar output,
`8 n_t` per trajectory output, and 10 bytes of status, steps and solver; a sweep whose
result, or whose chunk's working memory (`plan.chunk_bytes`, about `chunk * num_saves *
32` bytes, 104 with `peak_O`), exceeds half the host's memory is refused before any work
(`max_memory=` overrides). Beyond the result, a block of `SORT_BLOCK` samples needs about
30 MB of NumPy arrays on the host (measured) and about as much again for its
linearisation, whatever `n`.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..model.dynamics import Structure
from ..model.loads import SIDES
from ..runtime.lazy import lazy_import
from ..simulation import linearize, simulate
from ..solve.names import name_of
from ..solve.policy import SOLVERS, is_concrete, resolve_solver
from .checkpoint import Checkpoint, SharedCheckpoint, plan_manifest
from .collective import check_cluster, gather, on_process_0, same_everywhere, wait_for_coordinator
from .distributions import AbstractDistribution, whole
from .plan import SORT_BLOCK, VARIABLES, Plan, make_plan
from .reductions import DEFAULT_OUTPUTS, REDUCTIONS, TRAJECTORY_OUTPUTS, reduce
from .result import FAILED, MAX_STEPS, NONFINITE, OK, STATUS, Filling, SweepResult
from .trajectories import TrajectoryStore

diffrax = lazy_import("diffrax")  # imported on first use (see lazy.py)

__all__ = ["sweep", "SweepResult", "REDUCTIONS", "STATUS", "VARIABLES", "DEFAULT_OUTPUTS",
           "initialize_distributed", "sweep_cost"]


# ---------------------------------------------------------------------------------------
# Distribution over devices and hosts

_distributed_ready = False


def initialize_distributed(**kwargs) -> None:
    """Join a multi-host run: `jax.distributed.initialize(**kwargs)`, once.

    Call it before any other JAX call. Without arguments JAX reads the cluster from the
    environment (`JAX_COORDINATOR_ADDRESS`, `JAX_NUM_PROCESSES`, `JAX_PROCESS_ID`, or
    SLURM/MPI/cloud auto-detection). Afterwards `jax.devices()` lists every host's devices
    and a [`sweep`][] shards its chunks across all of them; every host draws the same
    samples from the seed and gets the whole result. Every process must call `sweep`
    with the same arguments: their plans' digests are compared before any work, and a
    mismatch is a `ValueError` on every process, naming what differs. A cluster JAX
    cannot join (a coordinator address that is not HOST:PORT, a process index outside the
    count) is a `ValueError` naming the argument or variable, before JAX is called.

    When a process dies in a sweep, the others' next collective fails and the sweep
    raises a `RuntimeError` saying a process was lost; when the coordinator (process 0)
    dies, JAX ends the other processes itself with an abort (at once when its socket
    closes, else within `heartbeat_timeout_seconds`, 100 s by default). The CLI turns
    both into one line.
    """
    global _distributed_ready
    if not _distributed_ready:
        check_cluster(kwargs)  # before JAX, which aborts or waits minutes on a bad value
        # JAX itself reads only the coordinator's address from the environment; the
        # documented JAX_NUM_PROCESSES and JAX_PROCESS_ID are read here.
        for key, env in (("num_processes", "JAX_NUM_PROCESSES"),
                         ("process_id", "JAX_PROCESS_ID")):
            if kwargs.get(key) is None and os.environ.get(env, "").strip():
                try:
                    kwargs[key] = int(os.environ[env])
                except ValueError:
                    raise ValueError(f"{env}={os.environ[env]!r} is not an integer") from None
        wait_for_coordinator(kwargs)  # JAX aborts the process when it cannot reach it
        jax.distributed.initialize(**kwargs)
        _distributed_ready = True


# ---------------------------------------------------------------------------------------
# The compiled chunk


@eqx.filter_jit
def _run_chunk(mech, load, torque, phi0, dphi0, ts, rtol, atol, *, load_fixed, torque_fixed,
               solver, structure, reductions, max_steps):
    """One chunk (or one device's part of one, see [`_Devices`][]): `_solve_chunk`, the
    same program on one device or several."""
    return _solve_chunk(mech, load, torque, phi0, dphi0, ts, rtol, atol,
                        load_fixed=load_fixed, torque_fixed=torque_fixed, solver=solver,
                        structure=structure, reductions=reductions, max_steps=max_steps)


def _solve_chunk(mech, load, torque, phi0, dphi0, ts, rtol, atol, *, load_fixed,
                 torque_fixed, solver, structure, reductions, max_steps):
    extras = ("reactions",) if "peak_O" in reductions else ()

    def one(mech, load, torque, phi0, dphi0):
        traj = simulate(mech, phi0, dphi0, ts, load=load, torque=torque, solver=solver,
                        rtol=rtol, atol=atol, max_steps=max_steps, outputs=extras,
                        structure=structure, throw=False)
        out = {name: reduce(name, traj, mech) for name in reductions}
        ok = traj.result == diffrax.RESULTS.successful
        finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(v)) for v in out.values()])) \
            if out else jnp.array(True)
        status = jnp.where(
            ~ok,
            jnp.where(traj.result == diffrax.RESULTS.max_steps_reached, MAX_STEPS, FAILED),
            jnp.where(finite, OK, NONFINITE)).astype(jnp.int8)
        # Never hand out NaN or inf: a sample that did not finish reads 0, and its status
        # says why.
        out = {k: jnp.where(status == OK, v, 0.0) for k, v in out.items()}
        return out, status, traj.num_steps

    axes = (0, None if load_fixed else 0, None if torque_fixed else 0, 0, 0)
    return jax.vmap(one, in_axes=axes)(mech, load, torque, phi0, dphi0)


def _stored_lin(solver, mech, load):
    """The linearisation `"auto"` needs, through the front door's stored program (the
    policy's own would trace it again in every process), else None."""
    return linearize(mech, load) if solver == "auto" and is_concrete((mech, load)) else None


def _fixed(plan: Plan) -> dict[str, bool]:
    return {f"{side}_fixed": plan.loads[side] is None for side in SIDES}


class _Devices:
    """The devices a sweep runs on, and this process's share of them.

    Each device runs the one-device program on its equal part of a chunk; JAX dispatches
    each call without waiting, so the devices run at once, and each device's step loop
    runs until *its* slowest member is done. Why not one program over a mesh: letting XLA
    partition the batched solve makes its step loops agree on their condition across
    devices at every step (a collective per step; measured on 2*10^4 lab rigs over two CPU
    devices, slower than one device), and a `shard_map` body is traced under a manual
    mesh, where arrays closed over from outside and library code that builds its own
    (a load's `zeros_like(t)`, lineax's structure checks in an implicit solver) fail. The
    same program on every device also gives bit-identical results on one device or many.
    In a multi-process run each process runs the parts of its own devices and the parts
    are gathered from every process (`collective.gather`).
    """

    def __init__(self, devices):
        devices = list(devices)
        self.n = len(devices)
        me = jax.process_index()
        owners = [d.process_index for d in devices]
        if owners != sorted(owners) or len({owners.count(p) for p in set(owners)}) != 1:
            raise ValueError("devices must hold the same number of devices of every process, "
                             "grouped by process (as jax.devices() lists them)")
        self.slots = [(i, d) for i, d in enumerate(devices) if d.process_index == me]

    def run(self, part: int, batched, shared, **static):
        """`_run_chunk` on every local device, device `i` on samples `[i part, (i+1)
        part)` of `batched = (mech, load, torque, phi0, dphi0)` (a load that is not
        batched is whole, `static` says which); `shared = (ts, rtol, atol)`. Returns this
        process's results and every other process's, joined in device order, on the
        host."""
        whole = (False, static["load_fixed"], static["torque_fixed"], False, False)
        calls = []
        for i, d in self.slots:
            args = [x if w else jax.tree.map(lambda a, i=i: a[i * part:(i + 1) * part], x)
                    for x, w in zip(batched, whole, strict=True)]
            calls.append(_run_chunk(*jax.device_put((*args, *shared), d), **static))
        return gather(jax.tree.map(lambda *xs: np.concatenate([np.asarray(x) for x in xs]),
                                    *calls))


def _run_block(plan: Plan, cols, order, chunk, dev: _Devices, consts, max_steps, sink,
               ckpt=None, b0=0, store=None, trajectories=False):
    """Run the valid samples `order` of one block in chunks; `sink(idx, res, st, ns,
    solver_index)` receives each chunk's results (host arrays, `idx` into the block). With
    a [`Checkpoint`][] `ckpt`, a chunk saved there is read instead of computed, and each
    computed chunk is saved. With a [`TrajectoryStore`][] `store` (process 0 of a run
    that saves trajectories), each computed chunk's trajectories are written there before
    the chunk is checkpointed (so a checkpointed chunk has them), and every chunk is
    listed. `store` is `None` on the other processes of a run that saves them: they
    compute the trajectories (`trajectories=True`) for process 0 to gather."""
    reductions = plan.reductions
    if trajectories:
        reductions += tuple(k for k in TRAJECTORY_OUTPUTS if k not in reductions)
    for start in range(0, order.size, chunk):
        idx = order[start:start + chunk]
        if store is not None:
            store.chunks.append((b0, start))
        saved = ckpt.load(b0, start, idx) if ckpt is not None else None
        if saved is not None:
            sink(idx, *saved)
            continue
        # Pad the last chunk with its own first sample: one shape, one compilation.
        padded = np.concatenate([idx, np.full(chunk - idx.size, idx[0])])
        mech, load, torque, phi0, dphi0 = plan.batch({k: v[padded] for k, v in cols.items()})
        solver = resolve_solver(plan.solver, mech, plan.rtol, plan.atol, load=load,
                                torque=torque, ts=plan.ts, max_steps=int(max_steps),
                                batch_invariant=True, lin=_stored_lin(plan.solver, mech, load))
        res, st, ns = dev.run(chunk // dev.n, (mech, load, torque, phi0, dphi0), consts,
                              **_fixed(plan), solver=solver, structure=plan.structure,
                              reductions=reductions, max_steps=int(max_steps))
        m = idx.size
        if store is not None:
            store.save(b0, start, idx, {k: res[k][:m] for k in TRAJECTORY_OUTPUTS})
        got = ({k: res[k][:m] for k in plan.reductions}, st[:m], ns[:m],
               SOLVERS.index(name_of(solver)))
        if ckpt is not None:
            ckpt.save(b0, start, idx, *got)
        sink(idx, *got)


# ---------------------------------------------------------------------------------------
# The public functions


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
    max_memory: int | None = None,
    checkpoint: str | os.PathLike | None = None,
    save_trajectories: str | os.PathLike | None = None,
    trajectory_every: int = 1,
) -> SweepResult:
    """Simulate a [`Scene`][] for many sampled values at once.

    **Arguments:**

    - `scene`: the nominal scene; fields not in `samples` keep its values. Any load kind
      works; a varied load parameter must be one the scene's load has or can be promoted
      to (none -> constant -> harmonic), else a `ValueError` names the load's parameters;
      one that cannot change this scene's result (e.g. `tau1` with no frequency) is refused.
    - `samples`: name (see [`VARIABLES`][]) -> a distribution (e.g. `Normal(2.0, 0.1)` or
      `"normal(2.0,0.1)"`), a number, or an explicit (n,) array.
    - `outputs`: reductions to compute (see [`REDUCTIONS`][]); nothing else is computed.
    - `n`: number of samples (optional when `samples` holds arrays). `seed`: integer seed.
    - `t1`, `num_saves`: horizon (s) and number of uniform save times on [0, t1]; default
      the scene's. Peaks and the spectrum are taken over the saved times.
    - `solver`: one of `SOLVERS`; default the scene's, where `"auto"` is decided per
      chunk by the solver policy ([`resolve_solver`][]).
    - `max_steps`: step budget per sample; a sample that runs out gets status
      `"max_steps"` and the others are kept.
    - `chunk_size`: samples per compiled call (bounds device memory: about
      `chunk_size * num_saves * 16` bytes of trajectory per chunk); rounded up to a
      multiple of the number of devices.
    - `sort`: bucket samples by linearised fastest rate (within blocks of `SORT_BLOCK`).
    - `devices`: devices to shard each chunk over (default: all of `jax.devices()`, which
      spans every host after [`initialize_distributed`][]).
    - `progress`: show a tqdm bar on stderr. `callback(done, total)`: called per chunk.
    - `max_memory`: refuse (`ValueError`) a result, or one chunk's working memory
      (`plan.chunk_bytes`: it grows with `num_saves`), larger than this many bytes
      (default half the host's memory; see the module docstring for the sizes).
    - `checkpoint`: a directory where each finished chunk is saved (created if missing); a
      rerun of the same sweep computes only the chunks missing there, and a different
      sweep is refused (`ValueError` naming what differs). In a multi-process run
      process 0 alone reads and writes it. See `sweep/checkpoint.py`.
    - `save_trajectories`: a directory where every solved sample's `phi` and `dphi` at
      the save times `ts[::trajectory_every]` are written, chunk by chunk (`.npy` files
      and a manifest; read them lazily with [`load_trajectories`][]). They never stay in
      memory. Refused before any work when they would not fit on the disk (`ValueError`
      naming the size). With `checkpoint`, a resumed sweep keeps the chunks saved there.
      In a multi-process run process 0 alone writes them. See `sweep/trajectories.py`.
    - `trajectory_every`: keep every `trajectory_every`-th save time (>= 1).

    **Returns:** a [`SweepResult`][] in the original sample order.
    """
    _check_paths(checkpoint=checkpoint, save_trajectories=save_trajectories)
    max_steps = whole(max_steps, "max_steps", 1)
    trajectory_every = whole(trajectory_every, "trajectory_every", 1)
    plan = make_plan(scene, samples, outputs, n=n, seed=seed, t1=t1, num_saves=num_saves,
                     solver=solver, chunk_size=chunk_size, sort=sort, max_memory=max_memory)
    n = plan.n
    dev = _Devices(list(jax.devices() if devices is None else devices))
    chunk = int(math.ceil(min(chunk_size, n) / dev.n) * dev.n)
    # Every process must run this very plan (each draws its samples from it), and take
    # part in the same collectives: refused on every process otherwise, before any work.
    same_everywhere(plan_manifest(plan, chunk, max_steps) | {
        "devices": dev.n, "checkpoint": checkpoint is not None,
        "save_trajectories": save_trajectories is not None,
        "trajectory_every": int(trajectory_every)}, "sweep")
    ckpt = None
    if checkpoint is not None:
        ckpt = (Checkpoint if jax.process_count() == 1 else SharedCheckpoint)(
            checkpoint, plan, chunk, max_steps)
    store = None
    if save_trajectories is not None:
        store = on_process_0(lambda: TrajectoryStore(
            save_trajectories, plan_manifest(plan, chunk, max_steps), plan.ts,
            trajectory_every, n), f"save_trajectories {str(save_trajectories)!r}")
        if ckpt is not None:
            ckpt.require = store.has if store is not None else None
    block = max(chunk, SORT_BLOCK // chunk * chunk)
    consts = (np.asarray(plan.ts), np.asarray(plan.rtol), np.asarray(plan.atol))
    results = Filling(plan, progress, callback)
    for b0 in range(0, n, block):
        b1 = min(b0 + block, n)
        drawn, cols, invalid, order = plan.block(b0, b1)
        results.drawn(b0, b1, drawn, invalid)
        _run_block(plan, cols, order, chunk, dev, consts, max_steps, results.sink(b0), ckpt,
                   b0, store, save_trajectories is not None)
    results.close()
    if store is not None:
        store.finish()
    return results.result()


def _check_paths(**paths) -> None:
    """`ValueError` naming the argument for an empty directory path."""
    for name, where in paths.items():
        # `Path("")` is the working directory: an empty path would scatter a sweep's
        # files there (the CLI's `--checkpoint ""` included).
        if where is not None and not os.fspath(where).strip():
            raise ValueError(f"{name}: the path is empty; give a directory (it is created "
                             "if missing), or leave it out")


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
    plan = make_plan(scene, samples, outputs, n=n, num_saves=num_saves, solver=solver,
                     sort=False)
    _, cols, _, _ = plan.block(0, plan.n)
    mech, load, torque, phi0, dphi0 = plan.batch(cols)
    lowered = _run_chunk.lower(
        mech, load, torque, jnp.asarray(phi0), jnp.asarray(dphi0), jnp.asarray(plan.ts),
        jnp.asarray(plan.rtol), jnp.asarray(plan.atol), **_fixed(plan), solver=plan.solver,
        structure=plan.structure if structure is None else structure,
        reductions=plan.reductions, max_steps=1000)
    compiled = lowered.compile().compiled  # equinox wraps jax.stages.Compiled
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    return {"flops": float(cost.get("flops", 0.0)),
            "transcendentals": float(cost.get("transcendentals", 0.0)),
            "bytes_accessed": float(cost.get("bytes accessed", 0.0)),
            "hlo_lines": float(len(compiled.as_text().splitlines()))}
