"""Levenberg-Marquardt as one JAX program, for many independent fits side by side.

[`fit_many`][crank_jax.fleet.many.fit_many] stacks the problems (single or multiple
shooting) of records of one shape (the same scene structure, free set, bucket length and
segment count) and runs
[`fleet_program`][] on them: `jax.vmap` of a `jax.lax.while_loop` LM, so the records'
ODE solves step side by side in one program (the lockstep solver's batch) and no host
round trip is paid per iteration.

Each member has its own damping, iteration count, stop test and status; one that is
done (converged, out of budget, failed) is frozen by the loop's select while the others
go on. The stop test is the host LM's ([`optimize`][crank_jax.identify.optimize]): the
Gauss-Newton step predicts a decrease below `DECREASE_FRACTION sigma^2` and moves no
coordinate by more than `STEP_FRACTION` of its standard error at the noise level (or,
whatever the noise, a step below `tol + tol |z|` in every coordinate).
"""

from __future__ import annotations

import threading
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..identify.fit_plan import start_solve
from ..identify.optimize import DECREASE_FRACTION, STEP_FRACTION
from ..identify.programs import Program, jacobian_at
from ..runtime.arrays import device_array

__all__ = ["STATUS", "FleetRun", "fleet_program", "stack", "shape_key", "BATCHES",
           "CPU_LARGEST", "largest_batch", "start_solves", "run_batch", "EXECUTION"]

#: A member's status at the end of [`fleet_program`][] (index into this tuple).
STATUS = ("converged", "budget", "failed", "stalled", "running")
_CONVERGED, _BUDGET, _FAILED, _STALLED, _RUNNING = range(5)
#: Damping beyond which a member that finds no lower cost has stalled.
_MAX_DAMPING = 1e16
#: The damping schedule, on the column-scaled `J / d` (its normal matrix has a unit
#: diagonal). A member starts undamped, with the Gauss-Newton step (as MINPACK's LM, the
#: single fit's, takes it while it lies inside its trust region); a rejected step damps
#: it at least `_DAMPING_AFTER_REJECT` (Nielsen's start, 1e-3 of that diagonal) and then
#: doubles as Nielsen's rule does; an accepted one divides the damping by up to
#: `1 / _DAMPING_DECREASE` (Marquardt's factor of 10). Nielsen's start with his floor of
#: 1/3 damped the weakly determined directions of a record near its minimum (a singular
#: value of 0.004 of the largest: a step of 2% of Gauss-Newton's at damping 1e-3) for five
#: or six accepted steps, each a full solve with sensitivities: measured on 100
#: rotating-rig records, 12 iterations a record at the median, against 4 here, to the
#: same stop test (experiments/bench_fit_many.py --rig rotating).
_DAMPING_AFTER_REJECT = 1e-3
_DAMPING_DECREASE = 0.1
#: Batch sizes of the compiled program: a group of records is cut into batches of at most
#: the largest, each padded (with copies of its first member) to the next size here, so a
#: few programs serve any count of records.
BATCHES = (4, 16, 32, 64)


#: Held around the fleet's compiled calls ([`run_batch`][], [`start_solves`][]), which
#: [`fit_many`][crank_jax.fleet.many.fit_many] makes from two threads (its plans, its
#: batches). Never two at once: a batched LAPACK kernel (the LM's SVD, an implicit
#: solver's LU) waits on XLA:CPU's intra-op threads for work it hands to the same
#: threads, so two of them at once on a pool of two threads wait forever (seen with
#: jax 0.10.2 on 2 cores: every thread of the pool in `ParallelBatchMap`). The plans'
#: other calls (the linearisation) hold no such kernel.
EXECUTION = threading.Lock()


#: The largest batch on the CPU. There a batch's members step one after another within
#: each lockstep step (no vector lanes across members), and a batch runs until its
#: slowest member is done, so a smaller batch costs less a member: 100 lab-rig records,
#: multiple shooting, 31.8, 35.1, 37.8 and 38.4 ms a member in batches of 4, 16, 32 and
#: 64; the rotating rig's 21-23 ms in all (2026-12-02, 2-core Xeon). 16 also lets
#: `fit_many` start fitting after 16 plans, not 64 (its plans overlap its fits).
CPU_LARGEST = 16


def largest_batch() -> int:
    """The most members one [`fleet_program`][] call steps side by side: [`CPU_LARGEST`][]
    on the CPU, the largest of [`BATCHES`][] on an accelerator (where a batch's members
    are the device's parallel lanes)."""
    return CPU_LARGEST if jax.default_backend() == "cpu" else BATCHES[-1]


class FleetRun(NamedTuple):
    """[`fleet_program`][]'s outcome, one row per member (host numpy arrays)."""

    z: np.ndarray  # (B, p) the last accepted point
    cost: np.ndarray  # (B,) 0.5 |r|^2 there
    iterations: np.ndarray  # (B,) LM steps tried (each one residual-and-Jacobian solve)
    status: np.ndarray  # (B,) index into STATUS
    decrease: np.ndarray  # (B,) the Gauss-Newton step's predicted decrease, sigma^2
    largest: np.ndarray  # (B,) its largest move over a standard error
    r: np.ndarray  # (B, N) the residuals at `z`
    J: np.ndarray  # (B, N, p) their sensitivities there


class _Svd(NamedTuple):
    """One SVD of the column-scaled `J / d` (Marquardt's scaling: `d` the columns' norms),
    and what the stop test reads from it: the Gauss-Newton step `dz`, its predicted
    decrease and its largest move over a standard error at the noise level."""

    S: jax.Array
    keep: jax.Array
    ur: jax.Array
    V: jax.Array
    dz: jax.Array
    dec: jax.Array
    big: jax.Array


def _svd(J, r, d, noise) -> _Svd:
    U, S, Vt = jnp.linalg.svd(J / d, full_matrices=False)
    keep = S > S[0] * jnp.finfo(J.dtype).eps * max(J.shape)
    inv = jnp.where(keep, 1.0 / jnp.where(keep, S, 1.0), 0.0)
    ur = U.T @ r
    V = Vt.T / d[:, None]  # back to the problem's coordinates
    dz = -V @ (inv * ur)
    se = noise * jnp.sqrt(jnp.sum((V * inv) ** 2, axis=1))
    se = jnp.where(se > 0, se, jnp.inf)
    dec = 0.5 * jnp.sum((ur * keep) ** 2)
    return _Svd(S, keep, ur, V, dz, dec, jnp.max(jnp.abs(dz) / se))


def _step(g: _Svd, lam):
    """The LM step with damping `lam`."""
    return -g.V @ (jnp.where(g.keep, g.S / (g.S**2 + lam), 0.0) * g.ur)


def _converged(g: _Svd, z, noise, tol):
    """The host LM's stop test (see the module's docstring)."""
    return ((g.dec <= DECREASE_FRACTION * noise**2) & (g.big <= STEP_FRACTION)) | jnp.all(
        jnp.abs(g.dz) <= tol + tol * jnp.abs(z))


class _State(NamedTuple):
    z: jax.Array
    r: jax.Array
    J: jax.Array
    cost: jax.Array
    d: jax.Array
    lam: jax.Array
    nu: jax.Array
    it: jax.Array
    status: jax.Array
    svd: _Svd


def _evaluate(problem, z):
    """(r, J, cost, ok) at `z`: the fit's own residuals-and-Jacobian function."""
    r, failed, _, J = jacobian_at.fn(problem, z)
    cost = 0.5 * jnp.sum(r * r)
    ok = (failed == 0) & jnp.isfinite(cost) & jnp.all(jnp.isfinite(J))
    return r, J, cost, ok


def _member(problem, z0, noise, tol, max_steps):
    """One member's LM loop (vmapped by `_fleet`). The stop test is judged at each point
    as it is accepted, so a member stops without another solve there."""
    r, J, cost, ok = _evaluate(problem, z0)
    d = jnp.maximum(jnp.linalg.norm(J, axis=0), 1e-300)
    g = _svd(J, r, d, noise)
    inf = jnp.full((), jnp.inf, z0.dtype)
    g = g._replace(dec=jnp.where(ok, g.dec, inf), big=jnp.where(ok, g.big, inf))
    status = jnp.where(ok, jnp.where(_converged(g, z0, noise, tol), _CONVERGED, jnp.where(
        max_steps <= 0, _BUDGET, _RUNNING)), _FAILED)
    s0 = _State(z0, r, J, cost, d, jnp.zeros((), z0.dtype), jnp.asarray(2.0, z0.dtype),
                jnp.asarray(0), status, g)

    def body(s: _State) -> _State:
        step = _step(s.svd, s.lam)
        zt = s.z + step
        rt, Jt, ct, okt = _evaluate(problem, zt)
        lin = s.r + s.J @ step
        pred = s.cost - 0.5 * jnp.sum(lin * lin)
        rho = (s.cost - ct) / jnp.where(pred > 0, pred, jnp.inf)
        take = okt & (ct < s.cost)
        lam = jnp.where(take, s.lam * jnp.maximum(_DAMPING_DECREASE, 1 - (2 * rho - 1) ** 3),
                        jnp.maximum(s.lam * s.nu, _DAMPING_AFTER_REJECT))
        nu = jnp.where(take, 2.0, 2 * s.nu)

        def pick(new, old):
            return jnp.where(take, new, old)

        z, r, J = pick(zt, s.z), pick(rt, s.r), pick(Jt, s.J)
        d = jnp.maximum(s.d, pick(jnp.linalg.norm(Jt, axis=0), s.d))
        g, it = _svd(J, r, d, noise), s.it + 1
        status = jnp.where(~take & (lam > _MAX_DAMPING), _STALLED, jnp.where(
            _converged(g, z, noise, tol), _CONVERGED,
            jnp.where(it >= max_steps, _BUDGET, _RUNNING)))
        return _State(z, r, J, pick(ct, s.cost), d, lam, nu, it, status, g)

    s = jax.lax.while_loop(lambda s: s.status == _RUNNING, body, s0)
    return s.z, s.cost, s.it, s.status, s.svd.dec / noise**2, s.svd.big, s.r, s.J


def _fleet(problems, z0, noise, tol, max_steps):
    return jax.vmap(_member, in_axes=(0, 0, 0, None, None))(problems, z0, noise, tol,
                                                           max_steps)


#: `fleet_program(problems, z0 (B, p), noise (B,), tol, max_steps)`, compiled and kept
#: between processes (see [`Program`][crank_jax.identify.programs.Program]).
fleet_program = Program(_fleet, "fleet_lm")


def shape_key(problem) -> tuple:
    """What must agree for problems to share a batch: the tree (scene structure, free
    names, solver, all static) and every leaf's shape and dtype."""
    leaves, treedef = jax.tree.flatten(problem)
    return treedef, tuple((np.shape(x), str(getattr(x, "dtype", np.asarray(x).dtype)))
                          for x in leaves)


def _stacked(xs):
    """Leaves of one shape stacked on the host, then copied to the device in one go (a
    weakly typed leaf by `jnp.stack`, which keeps it weak: the program's key holds each
    leaf's type)."""
    if getattr(xs[0], "weak_type", False):
        return jnp.stack([jnp.asarray(x) for x in xs])
    return device_array(np.stack([np.asarray(x) for x in xs]))


def stack(problems) -> object:
    """Problems of one [`shape_key`][] as one batched problem (a leading axis)."""
    return jax.tree.map(lambda *xs: _stacked(xs), *problems)


def run_batch(problems, z0s, noises, tol: float, max_steps: int) -> FleetRun:
    """[`fleet_program`][] on a list of problems of one [`shape_key`][] (at most
    [`largest_batch`][]), padded to a size of [`BATCHES`][] with copies of the first member
    (each member's result is its own: a copy steps exactly as its original)."""
    n = len(problems)
    size = next(b for b in BATCHES if b >= n)
    rows = list(range(n)) + [0] * (size - n)
    probs = stack([problems[i] for i in rows])
    z0 = device_array(np.stack([z0s[i] for i in rows]))
    noise = device_array(np.asarray([noises[i] for i in rows], dtype=z0.dtype))
    with EXECUTION:
        out = fleet_program(probs, z0, noise, jnp.asarray(tol, z0.dtype),
                            jnp.asarray(max_steps))
        return FleetRun(*(np.asarray(x)[:n] for x in out))


def _jacobians(problems, z):
    return jax.vmap(jacobian_at.fn)(problems, z)


#: `jacobians_program(problems, z (B, p))`: `jacobian_at` of each member, side by side.
jacobians_program = Program(_jacobians, "fleet_jacobians")


def start_solves(asks: list) -> list[tuple]:
    """[`start_solve`][crank_jax.identify.fit_plan.start_solve] of each `(problem, z)` of
    `asks` (problems of one [`shape_key`][]), side by side in batches of [`BATCHES`][]
    (padded with copies of the first). A batch with a member whose solve failed or is not
    finite is solved again member by member: no record's plan then depends on another's."""
    with EXECUTION:
        return _start_solves(asks)


def _start_solves(asks: list) -> list[tuple]:
    out, size = [], largest_batch()
    for k in range(0, len(asks), size):
        part = asks[k:k + size]
        if len(part) == 1:
            out.append(start_solve(*part[0]))
            continue
        pad = part + [part[0]] * (next(b for b in BATCHES if b >= len(part)) - len(part))
        res = jacobians_program(stack([p for p, _ in pad]),
                                jnp.asarray(np.stack([z for _, z in pad])))
        host = [np.asarray(x)[:len(part)] for x in res]
        rows = [tuple(h[j] for h in host) for j in range(len(part))]
        if not all(int(r[1]) == 0 and np.all(np.isfinite(r[0])) and np.all(np.isfinite(r[3]))
                   for r in rows):
            rows = [start_solve(*a) for a in part]
        out += rows
    return out
