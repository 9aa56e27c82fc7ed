"""The least-squares problem behind [`fit`][]: free parameters, their coordinates, and the
residual function (single or multiple shooting, one or several records).

Coordinates `z` (what the optimisers see, all O(1)):

- the twelve mechanism fields are positive, so they are fitted as `z = ln(value)`: a step
  in `z` is a relative change, positivity needs no constraint, and the columns of the
  Jacobian are the sensitivities *scaled by the parameter values* that the identifiability
  analysis needs;
- the initial states and load amplitudes are signed: `z = value / ref`, with `ref` a
  typical magnitude (the record's angle amplitude, that times the natural frequency, or
  the load's amplitude).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ..data import Data
from ..model.dynamics import Structure
from ..model.linear import linearize
from ..model.loads import LOAD_PARAMS, AbstractLoad, get_param, set_param
from ..model.params import FIELDS, SliderCrank
from ..solve.policy import resolve_solver
from ..solve.simulate import simulate

__all__ = ["STATE_NAMES", "LOAD_NAMES", "SCALE_GROUP", "Problem", "build_problem",
           "smooth_derivatives"]

STATE_NAMES = ("phi0", "dphi0")
#: Load parameters that can be free, name -> (side, role) from the load table
#: (`model.loads.LOAD_PARAMS`): each load's mean and amplitude (they enter linearly).
LOAD_NAMES = {n: sr for n, sr in LOAD_PARAMS.items() if sr[1] in ("mean", "amp")}
#: Parameters that enter the equation of motion linearly: scaling all of them (and every
#: load) by one factor leaves the motion unchanged (DESIGN.md section 3).
SCALE_GROUP = ("m_c", "m_p", "m_s", "I_c", "I_p", "k", "c")

# A failed solve gives NaN samples; a large finite residual instead makes the trust
# region reject that step, where a NaN could poison the linear algebra.
_FAILED_RESIDUAL = 10.0


def load_param(load: AbstractLoad, role: str) -> float | None:
    """The value of a load's `role` ("mean", "amp", ...), or None if its kind lacks it."""
    v = get_param(load, role)
    return None if v is None else float(v)


def set_load_param(load: AbstractLoad, role: str, value) -> AbstractLoad:
    """A copy of `load` with `role` set to `value` (see `model.loads.set_param`)."""
    return set_param(load, role, value)


class Segments(eqx.Module):
    """One record cut into `S` shooting segments of `m` save times each (padded).

    Segment `s` covers samples `starts[s] .. starts[s+1]` inclusive: the shared sample is
    fitted by segment `s+1` (weight 0 in segment `s`) and is where continuity is imposed.
    """

    ts: Array  # (S, m) save times, strictly increasing in each row
    phi: Array  # (S, m) data
    w: Array  # (S, m) 1 for a fitted sample, 0 for padding and the shared end sample
    end: Array  # (S,) int: index of the continuity sample in each row


def make_segments(ts: np.ndarray, phi: np.ndarray, n_segments: int) -> Segments:
    """Split a record into `n_segments` segments of nearly equal sample counts."""
    n = ts.shape[0]
    S = max(1, min(int(n_segments), n // 4))
    bounds = np.linspace(0, n - 1, S + 1).round().astype(int)
    m = int(np.max(np.diff(bounds))) + 1 if S > 1 else n
    T, P, W, E = (np.zeros((S, m)), np.zeros((S, m)), np.zeros((S, m)),
                  np.zeros(S, dtype=np.int32))
    for s in range(S):
        a, b = bounds[s], bounds[s + 1]
        k = b - a + 1 if S > 1 else n
        seg_t = ts[a:a + k]
        # Padding times continue just past the end, so each row stays strictly increasing
        # without extending the integration by more than a few nanoseconds.
        pad = seg_t[-1] + 1e-9 * np.arange(1, m - k + 1) * max(1.0, abs(seg_t[-1]))
        T[s] = np.concatenate([seg_t, pad])
        P[s, :k] = phi[a:a + k]
        W[s, :k] = 1.0
        if S > 1 and s < S - 1:
            W[s, k - 1] = 0.0  # the shared sample belongs to the next segment
        E[s] = k - 1
    return Segments(jnp.asarray(T), jnp.asarray(P), jnp.asarray(W), jnp.asarray(E))


class Experiment(eqx.Module):
    """One record in the problem: its segments, loads and fixed initial state."""

    seg: Segments
    load: AbstractLoad
    torque: AbstractLoad
    phi0: Array  # used when phi0 is not free
    dphi0: Array
    # Arrays, not static floats: a static value that depends on the data would recompile
    # every fit.
    ref_phi: Array
    ref_dphi: Array
    n: int = eqx.field(static=True)  # number of samples


class Problem(eqx.Module):
    """The residual function `z -> r` of a fit (an `eqx.Module`, so it can be jitted, and
    called as `problem(z, args) -> (r, None)` the way optimistix expects).

    `r` stacks, for every record and segment, `phi_model(t_i) - phi_i` at the fitted
    samples, then the continuity defects of multiple shooting.
    """

    base: SliderCrank
    exps: tuple[Experiment, ...]
    ref: Array  # (p,) scale of each coordinate; 1 for log coordinates
    names: tuple[str, ...] = eqx.field(static=True)  # reported names, (p,)
    log: tuple[bool, ...] = eqx.field(static=True)
    n_global: int = eqx.field(static=True)  # mechanism + load entries of z
    state_free: tuple[bool, bool] = eqx.field(static=True)
    solver: str = eqx.field(static=True)
    structure: Structure = eqx.field(static=True)
    rtol: Array
    atol: Array
    max_steps: int = eqx.field(static=True)
    adjoint: str = eqx.field(static=True, default="forward")

    # --- coordinates ------------------------------------------------------------------

    @property
    def p(self) -> int:
        """Number of reported parameters (excludes multiple-shooting segment states)."""
        return len(self.names)

    @property
    def n_extra(self) -> int:
        """Segment states of multiple shooting, appended after the reported parameters."""
        return sum(2 * (e.seg.ts.shape[0] - 1) for e in self.exps)

    @property
    def n_residuals(self) -> int:
        return sum(int(np.asarray(e.seg.w).sum()) for e in self.exps)

    def values(self, z: Array) -> Array:
        """Physical values of the reported parameters, shape (p,)."""
        return jnp.stack([jnp.exp(z[i]) if self.log[i] else z[i] * self.ref[i]
                          for i in range(self.p)])

    def to_z(self, values: Sequence[float]) -> np.ndarray:
        """Inverse of [`values`][]: physical values (p,) -> coordinates."""
        v = np.asarray(values, dtype=float)
        ref = np.asarray(self.ref)
        return np.where(self.log, np.log(np.where(self.log, v, 1.0)), v / ref)

    def unpack(self, z: Array):
        """(mechanism, [(load, torque, y0s)] per record) from coordinates `z`."""
        vals = self.values(z)
        fields = {n: getattr(self.base, n) for n in FIELDS}
        load_vals = {}
        for i, name in enumerate(self.names[:self.n_global]):
            if name in fields:
                fields[name] = vals[i]
            else:
                load_vals[name] = vals[i]
        mech = SliderCrank(**fields)
        out = []
        k = self.n_global
        x = self.p  # segment states start after the reported parameters
        for e in self.exps:
            load, torque = e.load, e.torque
            for name, v in load_vals.items():
                which, field = LOAD_NAMES[name]
                if which == "load":
                    load = set_load_param(load, field, v)
                else:
                    torque = set_load_param(torque, field, v)
            phi0, dphi0 = e.phi0, e.dphi0
            if self.state_free[0]:
                phi0 = vals[k]
                k += 1
            if self.state_free[1]:
                dphi0 = vals[k]
                k += 1
            S = e.seg.ts.shape[0]
            y0 = [jnp.stack([phi0, dphi0])]
            for _ in range(S - 1):
                y0.append(jnp.stack([z[x] * e.ref_phi, z[x + 1] * e.ref_dphi]))
                x += 2
            out.append((load, torque, jnp.stack(y0)))
        return mech, out

    # --- residuals --------------------------------------------------------------------

    def simulate_segments(self, mech, e: Experiment, load, torque, y0s):
        """Model angles and rates on every segment: (phi, dphi), each (S, m)."""
        def one(ts, y0):
            tr = simulate(mech, y0[0], y0[1], ts, load=load, torque=torque,
                          solver=self.solver, rtol=self.rtol, atol=self.atol,
                          max_steps=self.max_steps, adjoint=self.adjoint,
                          structure=self.structure, throw=False)
            return tr.phi, tr.dphi, tr.num_steps

        return jax.vmap(one)(e.seg.ts, y0s)

    def residuals(self, z: Array) -> tuple[Array, Array, Array]:
        """(r, n_failed, steps): the stacked residual vector, how many samples failed,
        and the most ODE steps any one solve took."""
        mech, per = self.unpack(z)
        rs, cont, failed, steps = [], [], 0, 0
        for e, (load, torque, y0s) in zip(self.exps, per):
            phi, dphi, n_steps = self.simulate_segments(mech, e, load, torque, y0s)
            steps = jnp.maximum(steps, jnp.max(n_steps))
            ok = jnp.isfinite(phi) & jnp.isfinite(dphi)
            failed = failed + jnp.sum(~ok & (e.seg.w > 0))
            r = jnp.where(ok, phi - e.seg.phi, _FAILED_RESIDUAL)
            # Padding and shared samples get weight 0: zeros in r change neither the sum of
            # squares nor the Jacobian's rank, and keep the shapes static.
            rs.append((e.seg.w * r).reshape(-1))
            S = e.seg.ts.shape[0]
            if S > 1:
                idx = e.seg.end[:-1]
                rows = jnp.arange(S - 1)
                # Continuity of the state at each shared sample, weighted like a segment's
                # worth of data so that the defects end up well below the noise.
                wgt = math.sqrt(e.seg.ts.shape[1])
                dphi_end = jnp.where(ok[rows, idx], dphi[rows, idx], _FAILED_RESIDUAL)
                phi_end = jnp.where(ok[rows, idx], phi[rows, idx], _FAILED_RESIDUAL)
                cont.append(wgt * (phi_end - y0s[1:, 0]))
                cont.append(wgt * (dphi_end - y0s[1:, 1]) * (e.ref_phi / e.ref_dphi))
        return jnp.concatenate(rs + cont), failed, steps

    def __call__(self, z: Array, args=None):
        return self.residuals(z)[0], None


def smooth_derivatives(ts: np.ndarray, phi: np.ndarray, half: int):
    """Local quartic least-squares fits (a Savitzky-Golay filter for irregular samples).

    **Arguments:** `ts`, `phi` (n,); `half`, the half-width of the window in samples (the
    window is shifted inwards at the ends). **Returns:** `(phi, dphi, ddphi)`, each (n,).
    """
    n = ts.shape[0]
    w = min(max(2 * half + 1, 7), n)
    start = np.clip(np.arange(n) - half, 0, n - w)
    idx = start[:, None] + np.arange(w)[None, :]
    dt = ts[idx] - ts[:, None]
    h = np.maximum(np.abs(dt).max(axis=1, keepdims=True), 1e-12)
    x = dt / h  # scaled for conditioning
    # Quartic: a cubic's error in phi'' is ~25x larger over the same window.
    V = x[..., None] ** np.arange(5)
    A = np.einsum("nwi,nwj->nij", V, V)
    bvec = np.einsum("nwi,nw->ni", V, phi[idx])
    c = np.linalg.solve(A + 1e-12 * np.eye(5), bvec[..., None])[..., 0]
    hh = h[:, 0]
    return c[:, 0], c[:, 1] / hh, 2 * c[:, 2] / hh**2


def natural_period(mech: SliderCrank, load: AbstractLoad | None = None) -> float | None:
    """The linearised period 2 pi / omega_n, s, or None when phi = 0 is not stable."""
    lin = linearize(mech, load)
    w = float(np.asarray(lin.omega_n))
    return 2 * math.pi / w if math.isfinite(w) and w > 0 else None


def build_problem(
    mech: SliderCrank,
    records: Sequence[tuple[Data, AbstractLoad, AbstractLoad, float, float]],
    free: Sequence[str],
    start: dict[str, float],
    n_segments: Sequence[int],
    *,
    solver: str,
    rtol: float,
    atol: float,
    max_steps: int,
    adjoint: str = "forward",
) -> Problem:
    """Assemble a [`Problem`][].

    **Arguments:**

    - `mech`: fixed parameter values (free ones are overwritten from `start`).
    - `records`: per record `(data, load, torque, phi0, dphi0)`; the state is the start
      value (or the fixed value, when not free) at the record's first sample.
    - `free`: names from `FIELDS`, `LOAD_NAMES` and `STATE_NAMES`.
    - `start`: start value of every free global name, and `phi0[i]`/`dphi0[i]` per record.
    - `n_segments`: shooting segments per record (1 = single shooting).
    """
    glob = [n for n in free if n not in STATE_NAMES]
    state_free = (("phi0" in free), ("dphi0" in free))
    names, log, ref = [], [], []
    for n in glob:
        names.append(n)
        log.append(n in FIELDS)
        ref.append(1.0 if n in FIELDS else max(abs(start[n]), 1e-6))
    exps = []
    multi = len(records) > 1
    for i, (data, load, torque, phi0, dphi0) in enumerate(records):
        amp = max(float(np.max(np.abs(data.phi - np.mean(data.phi)))), 1e-3)
        period = natural_period(mech, load)
        span = float(data.ts[-1] - data.ts[0])
        omega = 2 * math.pi / (period if period is not None else span)
        ref_phi, ref_dphi = max(amp, abs(phi0)), max(amp * omega, abs(dphi0))
        for name, flag, r in (("phi0", state_free[0], ref_phi),
                              ("dphi0", state_free[1], ref_dphi)):
            if flag:
                names.append(f"{name}[{i}]" if multi else name)
                log.append(False)
                ref.append(r)
        seg = make_segments(data.ts, data.phi, n_segments[i])
        exps.append(Experiment(seg, load, torque, jnp.asarray(phi0, float),
                               jnp.asarray(dphi0, float), jnp.asarray(ref_phi, float),
                               jnp.asarray(ref_dphi, float), data.n))
    mech_start = mech.replace(**{n: start[n] for n in glob if n in FIELDS})
    structure = Structure.of(mech_start)
    return Problem(mech_start, tuple(exps), jnp.asarray(ref), tuple(names), tuple(log),
                   len(glob), state_free, solver, structure, jnp.asarray(rtol),
                   jnp.asarray(atol), int(max_steps), adjoint)


def pick_solver(mech: SliderCrank, load, rtol: float, solver: str) -> str:
    """The ODE solver of a fit: the scene's, or the automatic choice at the start values
    (the record's padded segment times are not a uniform grid, so no save times)."""
    return resolve_solver(solver, mech, rtol, load=load)
