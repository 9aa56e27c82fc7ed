"""The least-squares problem behind [`fit`][]: free parameters, their coordinates, and the
residual function (single or multiple shooting, one or several records).

Coordinates `z` (what the optimisers see, all O(1)), chosen per name by
[`coordinate`][]:

- a mechanism field that cannot be negative and starts positive is fitted as
  `z = ln(value)`: a step in `z` is a relative change, positivity needs no constraint,
  and the columns of the Jacobian are the sensitivities *scaled by the parameter values*
  that the identifiability analysis needs;
- everything else (a signed field such as the offset `e`, a field that starts at 0 such
  as a friction coefficient, the initial states and load amplitudes) is linear:
  `z = value / ref`, with `ref` a typical magnitude (the start value, the record's angle
  amplitude, that times the natural frequency).

Shapes are bucketed (each record is padded to one of a few lengths with samples of weight
0), so records of other lengths reuse the compiled programs; and the ODE solve carries no
host callback (no `eqx.error_if`), so JAX's persistent cache can keep those programs
between processes.
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
from ..lazy import lazy_import
from ..model.dynamics import CrankField, Structure
from ..model.linear import linearize
from ..model.loads import AbstractLoad, nonsmooth_times, set_param
from ..model.params import FIELDS, SliderCrank
from ..solve.policy import resolve_solver
from .request import LOAD_NAMES, SIGNED_FIELDS
from .segments import Segments, make_segments, padded_load

diffrax = lazy_import("diffrax")  # imported on first use (see lazy.py)

__all__ = ["Problem", "Experiment", "build_problem", "coordinate", "natural_period",
           "linear_frequency", "pick_solver"]

# A failed solve gives NaN samples; a large finite residual instead makes the trust
# region reject that step, where a NaN could poison the linear algebra.
_FAILED_RESIDUAL = 10.0
# Linear scale of a mechanism field that starts at 0 (a friction coefficient, an offset
# in units of r): the optimiser's first steps are O(1) in z.
_ZERO_START_REF = 1e-3
_TINY = 1e-9


def coordinate(name: str, start: float, mech: SliderCrank, omega: float | None = None
               ) -> tuple[bool, float]:
    """`(log, ref)` of a global free name: log coordinates for a mechanism field that
    cannot be negative and starts positive; otherwise linear with scale `ref`.

    A field that starts at 0 takes its scale from the record's observed angular frequency
    `omega` (rad/s) and the linearised inertia `mu`: `mu omega^2` for k, 5% damping
    (`0.1 mu omega`) for c; an offset e takes a tenth of r.
    """
    if name in FIELDS and name not in SIGNED_FIELDS and start > 0:
        return True, 1.0
    if start != 0:
        return False, abs(start)
    if name in SIGNED_FIELDS:
        return False, 0.1 * float(mech.r)
    if omega and name in ("k", "c"):
        mu = float(np.asarray(linearize(mech).mu))
        if math.isfinite(mu) and mu > 0:
            return False, mu * omega**2 if name == "k" else 0.1 * mu * omega
    return False, _ZERO_START_REF


def _fit_field(t, y, field):
    """The fit's own ODETerm adapter on the model's vector field (a function object of its
    own: diffrax caches traces by it, see `Problem.simulate_segments`)."""
    return jnp.stack(field(t, (y[0], y[1])))


def _fit_field_no_callbacks(t, y, field):
    """As `_fit_field`, for traces made with equinox's checks as NaN
    (`persistent.checks_without_callbacks`): a separate object, so a trace made in one mode
    (with host callbacks) is never reused in the other."""
    return jnp.stack(field(t, (y[0], y[1])))


def _ode_term() -> diffrax.ODETerm:
    from ..compat import checks_are_nan  # the switch `checks_without_callbacks` sets

    nan = checks_are_nan()
    return diffrax.ODETerm(_fit_field_no_callbacks if nan else _fit_field)


# The fit's residuals use diffrax's adaptive solvers; "dopri8-uniform" (uniform save
# times only) runs as the same Dopri8 tableau, adaptively, on the padded segment times.
_SOLVERS = {"tsit5": "Tsit5", "dopri5": "Dopri5", "dopri8": "Dopri8",
            "dopri8-uniform": "Dopri8", "dopri8-adaptive": "Dopri8", "kvaerno5": "Kvaerno5"}


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

    @property
    def n(self) -> int:
        """Number of fitted samples (host side)."""
        return int(np.asarray(self.seg.w).sum())




class Problem(eqx.Module):
    """The residual function `z -> r` of a fit (an `eqx.Module`, so it can be jitted).

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
                side, role = LOAD_NAMES[name]
                if side == "load":
                    load = set_param(load, role, v, side)
                else:
                    torque = set_param(torque, role, v, side)
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
        """Model angles and rates on every segment: (phi, dphi), each (S, m), NaN after a
        failed solve, and the ODE steps each segment's solve took (S,).

        diffrax directly, on the model's `CrankField`, rather than through `simulate`:
        traced with equinox's checks off (`persistent.checks_without_callbacks`), the fit's
        programs must share no trace with a user's `simulate` (measured: routing them
        through `simulate` let a host callback into a later fit program, or NaN-mode
        checks into a later user program). The solver name comes from the one policy
        (`pick_solver`) and the step clipping at load kinks is the loads' own
        (`nonsmooth_times`). A trial point outside the valid set fails its solve, which
        the residuals turn into a rejection."""
        step_ts, jump_ts = nonsmooth_times(load, torque)
        controller = diffrax.PIDController(rtol=self.rtol, atol=self.atol)
        if step_ts is not None or jump_ts is not None:
            controller = diffrax.ClipStepSizeController(controller, step_ts=step_ts,
                                                        jump_ts=jump_ts)
        adjoint = (diffrax.ForwardMode() if self.adjoint == "forward"
                   else diffrax.RecursiveCheckpointAdjoint())
        field = CrankField(mech, load, torque, self.structure).packed()

        def one(ts, y0):
            sol = diffrax.diffeqsolve(
                _ode_term(), getattr(diffrax, _SOLVERS[self.solver])(), t0=ts[0],
                t1=ts[-1], dt0=None, y0=y0, args=field, saveat=diffrax.SaveAt(ts=ts),
                stepsize_controller=controller, max_steps=self.max_steps, adjoint=adjoint,
                throw=False)
            ok = sol.result == diffrax.RESULTS.successful
            return (jnp.where(ok, sol.ys[:, 0], jnp.nan), jnp.where(ok, sol.ys[:, 1], jnp.nan),
                    sol.stats["num_steps"])

        if e.seg.ts.shape[0] == 1:
            # Single shooting: one solve, not a batch of one (a vmap of a solve of size 1
            # still traces the batching of every loop in it: ~20% of tracing the fit).
            return tuple(x[None] for x in one(e.seg.ts[0], y0s[0]))
        return jax.vmap(one)(e.seg.ts, y0s)

    def fitted(self, r) -> list[np.ndarray]:
        """Model angles at each record's samples, from single-shooting residuals `r`
        (r = model - data), rad."""
        out, k = [], 0
        for e in self.exps:
            size = int(np.prod(e.seg.ts.shape))
            out.append(np.asarray(e.seg.phi[0, :e.n]) + np.asarray(r)[k:k + e.n])
            k += size
        return out

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


def linear_frequency(mech: SliderCrank, load: AbstractLoad | None = None) -> float | None:
    """The linearised natural frequency omega_n, rad/s, or None when phi = 0 is not a
    stable equilibrium."""
    period = natural_period(mech, load)
    return 2 * math.pi / period if period is not None else None


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
    pad: bool = True,
    omega: float | None = None,
) -> Problem:
    """Assemble a [`Problem`][].

    **Arguments:**

    - `mech`: fixed parameter values (free ones are overwritten from `start`).
    - `records`: per record `(data, load, torque, phi0, dphi0)`; the state is the start
      value (or the fixed value, when not free) at the record's first sample.
    - `free`: names from `FIELDS`, `LOAD_NAMES` and `STATE_NAMES`.
    - `start`: start value of every free global name.
    - `n_segments`: shooting segments per record (1 = single shooting).
    - `solver`, `rtol`, `atol`, `max_steps`: the ODE solve; `adjoint`: `"forward"` (for
      Jacobians) or `"reverse"` (for gradients).
    - `pad`: pad each record to a [`bucket`][] length (weight-0 samples), so that records
      of other lengths reuse the compiled programs.
    - `omega`: the records' observed angular frequency, rad/s (scales a free field that
      starts at 0; see [`coordinate`][]).
    """
    glob = [n for n in free if n not in ("phi0", "dphi0")]
    state_free = (("phi0" in free), ("dphi0" in free))
    names, log, ref = [], [], []
    for n in glob:
        lg, rf = coordinate(n, float(start[n]), mech, omega)
        names.append(n)
        log.append(lg)
        ref.append(rf)
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
        seg = make_segments(data.ts, data.phi, n_segments[i], pad)
        exps.append(Experiment(seg, padded_load(load) if pad else load,
                               padded_load(torque) if pad else torque,
                               jnp.asarray(phi0, float), jnp.asarray(dphi0, float),
                               jnp.asarray(ref_phi, float), jnp.asarray(ref_dphi, float)))
    mech_start = mech.replace(**{n: start[n] for n in glob if n in FIELDS})
    # A zero is structure (the compiled program leaves its term out), but a free field
    # that starts at 0 must keep its term, or its sensitivity would be exactly zero.
    nonzero = mech_start.replace(**{n: _TINY for n in glob if n in FIELDS and start[n] == 0})
    structure = Structure.of(mech_start).union(Structure.of(nonzero))
    return Problem(mech_start, tuple(exps), jnp.asarray(ref), tuple(names), tuple(log),
                   len(glob), state_free, solver, structure, jnp.asarray(rtol),
                   jnp.asarray(atol), int(max_steps), adjoint)


def pick_solver(mech: SliderCrank, load, rtol: float, solver: str) -> str:
    """The ODE solver of a fit: the scene's, or the automatic choice at the start values
    (the record's padded segment times are not a uniform grid, so no save times)."""
    name = resolve_solver(solver, mech, rtol, load=load)
    return "dopri8" if name in ("dopri8-uniform", "dopri8-adaptive") else name
