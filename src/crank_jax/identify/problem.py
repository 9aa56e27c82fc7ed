"""The least-squares problem behind [`fit`][]: free parameters, their coordinates, and the
residual function (single or multiple shooting, one or several records).

Coordinates `z` (what the optimisers see, all O(1)) are chosen per name in
[`coordinates`][crank_jax.identify.coordinates]: log, folded or linear.

Every trial point is also checked against the mechanism's validation rules (e.g.
`b <= L`, `L > r + |e|`) inside the compiled residuals: a point outside them counts as a
failed solve, which the optimiser rejects, so no iterate the fit reports is invalid.

Shapes are bucketed (each record is padded to one of a few lengths with samples of weight
0), so records of other lengths reuse the compiled programs; and the ODE solve is
`simulate`'s own core without its runtime checks, so with the fused solvers and diffrax's
explicit ones the programs hold no host callback and JAX's persistent cache can keep them
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

from ..model.dynamics import Structure
from ..model.loads import AbstractLoad, set_param
from ..model.params import FIELDS, SliderCrank, validation_rules
from ..records.data import Data
from ..records.sensors import OFFSET_NAMES
from ..runtime.arrays import device_array
from ..simulation import linearize
from ..solve import AbstractAdjoint, AbstractSolver, AdaptiveDopri8, ForwardSensitivities
from ..solve.policy import is_concrete, resolve_solver
from ..solve.trajectory import solve_crank
from .coordinates import coordinates, values_of, values_program
from .measurement import calibration, channel_errors, fitted_channels
from .request import LOAD_NAMES, record_mech
from .segments import Experiment, make_segments, padded_load
from .userforce import PREFIX, with_force_values

__all__ = ["Problem", "Experiment", "build_problem", "natural_period", "linear_frequency",
           "pick_solver"]

# A failed solve gives NaN samples; a large finite residual instead makes the trust
# region reject that step, where a NaN could poison the linear algebra.
_FAILED_RESIDUAL = 10.0
_TINY = 1e-9


def _invalid(mech: SliderCrank) -> Array:
    """True when a (traced) mechanism breaks a validation rule of `model.params`."""
    bad = [jnp.any(mask) for _, mask, _ in validation_rules(
        {n: jnp.asarray(getattr(mech, n)) for n in FIELDS})]
    return jnp.any(jnp.stack(bad))


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
    solver: AbstractSolver = eqx.field(static=True)
    structure: Structure = eqx.field(static=True)
    rtol: Array
    atol: Array
    max_steps: int = eqx.field(static=True)
    adjoint: AbstractAdjoint = eqx.field(static=True, default=ForwardSensitivities())
    # Per reported name: fitted as `ref |z|` (see `folded`); empty: none is.
    fold: tuple[bool, ...] = eqx.field(static=True, default=())
    # Free names with one value per record (`name[i]`, before each record's states).
    per_record: tuple[str, ...] = eqx.field(static=True, default=())
    force: object = None  # a user's force term (`userforce.py`), its free fields set by z

    @property
    def p(self) -> int:
        """Reported parameters (excludes multiple-shooting segment states)."""
        return len(self.names)

    @property
    def n_extra(self) -> int:
        """Segment states of multiple shooting, appended after the reported parameters."""
        return sum(2 * (e.seg.ts.shape[0] - 1) for e in self.exps)

    @property
    def state_on(self) -> np.ndarray:
        """(n_extra,) bool: False for an inactive row's state (see `segment_layout`)."""
        return np.concatenate([np.repeat(np.asarray(e.seg.on)[1:] > 0, 2) for e in self.exps])

    @property
    def n_residuals(self) -> int:
        return sum(int(np.asarray(e.seg.w).sum()) * len(e.channels) for e in self.exps)

    @property
    def folded(self) -> tuple[bool, ...]:
        """(p,) whether each reported name is fitted as `ref |z|`."""
        return self.fold or (False,) * self.p

    def values(self, z: Array) -> Array:
        """Physical values of the reported parameters, shape (p,)."""
        return values_of(z, self.ref, self.log[:self.p], self.folded)

    def host_values(self, z) -> np.ndarray:
        """[`values`][] of host coordinates `z` (p,) or longer, as numpy: one compiled
        program of the same arithmetic, where the eager operations compiled five small
        programs (a noticeable part of a cold fit: docs/benchmarks/design-figures.md)."""
        # The whole `z` goes in: `values_of` reads its first p entries (a slice here would
        # be one more small program).
        return np.asarray(values_program(device_array(z), self.ref, self.log[:self.p],
                                          self.folded))

    def host_mech(self, z) -> SliderCrank:
        """The mechanism of host coordinates `z`: [`unpack`][]'s first part, its fields
        from [`host_values`][] (the same numbers, with no small program compiled per
        operation)."""
        return self._mech(self.host_values(z))

    def _mech(self, vals) -> SliderCrank:
        """The base mechanism with the global names' values `vals` (p,) in its fields."""
        return self.base.replace(**{n: vals[i] for i, n in
                                    enumerate(self.names[:self.n_global]) if n in FIELDS})

    def to_z(self, values: Sequence[float]) -> np.ndarray:
        """Inverse of [`values`][]: physical values (p,) -> coordinates (a folded value's
        non-negative branch)."""
        v = np.asarray(values, dtype=float)
        ref = np.asarray(self.ref)
        return np.where(self.log, np.log(np.where(self.log, v, 1.0)), v / ref)

    def unpack(self, z: Array):
        """(mechanism, [(load, torque, y0s, own)] per record) from coordinates `z`; `own`:
        every value but the shared mechanism fields' (name -> value), and under `"force."`
        the record's force term."""
        vals = self.values(z)
        mech = self._mech(vals)
        load_vals = {name: vals[i] for i, name in enumerate(self.names[:self.n_global])
                     if name not in FIELDS}
        out = []
        k = self.n_global
        x = self.p  # segment states start after the reported parameters
        for e in self.exps:
            load, torque = e.load, e.torque
            own = {**load_vals, **{n: vals[k + j] for j, n in enumerate(self.per_record)}}
            force = with_force_values(self.force, {n: v for n, v in own.items()
                                                   if n.startswith(PREFIX)})
            k += len(self.per_record)
            for name, v in own.items():
                if name not in LOAD_NAMES:
                    continue
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
            out.append((load, torque, jnp.stack(y0), {**own, PREFIX: force}))
        return mech, out

    # --- residuals --------------------------------------------------------------------

    def simulate_segments(self, mech, e: Experiment, load, torque, y0s, force=None):
        """Model angles and rates on every segment: (phi, dphi), each (S, m), NaN after a
        failed solve, and the ODE steps each segment's solve took (S,).

        Through `simulate`'s solve core ([`solve_crank`][]): the solver the one policy
        chose (`pick_solver`), its derivative rules (forward mode of `"dopri8-adaptive"`
        steps the variational equation), the step clipping at load kinks. It holds no
        runtime check, so the fused solvers' programs hold no host callback, nor do diffrax's
        explicit solvers' in forward mode (`solve/saves.py`). A trial point
        outside the valid set fails its solve, which the residuals turn into a
        rejection."""

        def one(ts, y0):
            traj = solve_crank(mech, load, torque, force, y0, ts, self.rtol, self.atol,
                               solver=self.solver, max_steps=self.max_steps,
                               adjoint=self.adjoint, structure=self.structure)
            ok = traj.ok
            return (jnp.where(ok, traj.phi, jnp.nan), jnp.where(ok, traj.dphi, jnp.nan),
                    traj.num_steps)

        if e.seg.ts.shape[0] == 1:
            # Single shooting: one solve, not a batch of one (a vmap of a solve of size 1
            # still traces the batching of every loop in it: ~20% of tracing the fit).
            return tuple(x[None] for x in one(e.seg.ts[0], y0s[0]))
        return jax.vmap(one)(e.seg.ts, y0s)

    @property
    def n_rows(self) -> int:
        """Length of the residual vector: every record's padded samples in each channel,
        then the continuity defects (see [`residuals`][]); `n_residuals` counts fitted
        samples."""
        return sum(int(np.prod(e.seg.ts.shape)) * len(e.channels)
                   for e in self.exps) + self.n_extra

    def no_residuals(self) -> np.ndarray:
        """NaN residuals of the right length, for a fit with no solve to show (n_rows,)."""
        return np.full(self.n_rows, np.nan)

    def fitted(self, r) -> list[np.ndarray]:
        """The first channel's model reading at each record's samples (the model angle,
        rad, for a plain angle record), from single-shooting residuals `r`."""
        return [next(iter(f.values())) for f in fitted_channels(self, r)]

    def residuals(self, z: Array) -> tuple[Array, Array, Array]:
        """(r, n_failed, steps): the stacked residual vector, how many samples failed,
        and per record the most ODE steps any one of its solves took, (R,) (so that a
        record the start values cannot follow is found by itself, see
        `plan.make_plan`)."""
        mech, per = self.unpack(z)
        rs, cont, failed, steps = [], [], 0, []
        # A point outside the mechanism's valid set (a coupler shorter than the crank, a
        # centre of mass beyond the coupler) is a failed solve: rejected, never reported.
        for e, (load, torque, y0s, own) in zip(self.exps, per):
            mech_e = record_mech(mech, own)
            offsets_e = {OFFSET_NAMES[n]: v for n, v in own.items() if n in OFFSET_NAMES}
            invalid = _invalid(mech_e)
            force = own.pop(PREFIX)
            phi, dphi, n_steps = self.simulate_segments(mech_e, e, load, torque, y0s, force)
            steps.append(jnp.max(n_steps))
            ok = jnp.isfinite(phi) & jnp.isfinite(dphi) & ~invalid
            failed = failed + jnp.sum(~ok & (e.seg.w > 0))
            err = channel_errors(mech_e, e, load, torque, phi, dphi, offsets_e, self.structure,
                                 force)
            r = jnp.where(ok[None], err * e.weight[:, None, None], _FAILED_RESIDUAL)
            # Padding and shared samples get weight 0: zeros in r change neither the sum of
            # squares nor the Jacobian's rank, and keep the shapes static.
            rs.append((e.seg.w[None] * r).reshape(-1))
            S = e.seg.ts.shape[0]
            if S > 1:
                idx = e.seg.end[:-1]
                rows = jnp.arange(S - 1)
                # Continuity of the state at each shared sample, weighted like a segment's
                # worth of data so that the defects end up well below the noise.
                # In the first channel's unit (its reading's change per radian), so the
                # defects weigh against the data alike whatever the sensor.
                wgt = jnp.sqrt(e.seg.size) * e.per_radian * e.seg.on[1:]
                dphi_end = jnp.where(ok[rows, idx], dphi[rows, idx], _FAILED_RESIDUAL)
                phi_end = jnp.where(ok[rows, idx], phi[rows, idx], _FAILED_RESIDUAL)
                cont.append(wgt * (phi_end - y0s[1:, 0]))
                cont.append(wgt * (dphi_end - y0s[1:, 1]) * (e.ref_phi / e.ref_dphi))
        return jnp.concatenate(rs + cont), failed, jnp.stack(steps)


def linear_frequency(lin) -> float | None:
    """The natural frequency omega_n of the linearisation `lin`, rad/s (2 pi over
    [`natural_period`][]'s), or None when its equilibrium is not stable."""
    period = natural_period(lin)
    return 2 * math.pi / period if period is not None else None


def natural_period(lin) -> float | None:
    """The period 2 pi / omega_n of the linearisation `lin`, s; None if it is unstable."""
    w = float(np.asarray(lin.omega_n))
    return 2 * math.pi / w if math.isfinite(w) and w > 0 else None


def build_problem(
    mech: SliderCrank,
    records: Sequence[tuple[Data, AbstractLoad, AbstractLoad, float, float]],
    free: Sequence[str],
    start: dict[str, float],
    n_segments: Sequence[int],
    *,
    solver: AbstractSolver | str,
    rtol: float,
    atol: float,
    max_steps: int,
    adjoint: AbstractAdjoint = ForwardSensitivities(),
    pad: bool = True,
    omega: float | None = None,
    angles: Sequence[np.ndarray] | None = None,
    sigmas: dict[str, float] | None = None,
    per_record: Sequence[str] = (),
    force=None,
    linear: bool = False,
    torque: float | None = None,
) -> Problem:
    """Assemble a [`Problem`][].

    **Arguments:**

    - `mech`: fixed parameter values (free ones are overwritten from `start`).
    - `records`: per record `(data, load, torque, phi0, dphi0)`; the state is the start
      value (or the fixed value, when not free) at the record's first sample.
    - `free`: names from `FIELDS`, `LOAD_NAMES` and `STATE_NAMES`.
    - `start`: start value of every free global name.
    - `n_segments`: shooting segments per record (1 = single shooting).
    - `solver`, `rtol`, `atol`, `max_steps`: the ODE solve (`solver` a solver object,
      [`pick_solver`][]'s, or a name the policy resolves at `mech`); `adjoint`: an adjoint
      object, `ForwardSensitivities()` (Jacobians) or a `DiscreteAdjoint` (gradients).
    - `pad`: pad each record to a [`bucket`][crank_jax.identify.segments.bucket] length
      (weight-0 samples), so that records of other lengths reuse the compiled programs.
    - `omega`: the records' observed angular frequency, rad/s (scales a free field that
      starts at 0; see [`coordinate`][]).
    - `angles`: each record's crank angle as far as the data tell (n,), rad (default: its
      `phi`): the scale of the state coordinates.
    - `sigmas`: each channel's noise level, SI (default 1 each): a channel's residuals
      are weighted by the first channel's level over its own.
    - `per_record`: free names with a separate value per record (`name[i]`).
    - `force`: a user's force term (its free fields are `force.<field>` names).
    - `linear`: every coordinate linear in its value (none in log space; see
      `coordinates`). Multiple shooting optimises in these: the dynamics are linear in
      the mechanism's coefficients (damping, friction, motor gain, inertias), so in them
      the valley of a constant mean speed, `gain u - T_c = c dphi`, is straight, where in
      log coordinates it curves and LM crawls along it (56 iterations instead of 16-28 on
      the rotating rig, experiments/results/fit_speed.json). Single shooting, whose
      coordinates the polish, the intervals and the identifiability use, keeps log ones.
    - `torque`: the records' torque scale, N*m (the unit of a load that starts at 0; see
      [`coordinate`][]).
    """
    per_record = tuple(per_record)
    glob = [n for n in free if n not in ("phi0", "dphi0") and n not in per_record]
    omega_obs = omega
    state_free = (("phi0" in free), ("dphi0" in free))
    names, log, ref, fold = [], [], [], []
    for n in glob:
        lg, rf, fd = coordinates(n, float(start[n]), mech, omega, linear, torque)
        names.append(n)
        log.append(lg)
        ref.append(rf)
        fold.append(fd)
    exps = []
    multi = len(records) > 1
    first = records[0][0].outputs()[0][0].name
    first_sigma = (sigmas or {}).get(first, 1.0)
    for i, (data, load, torque, phi0, dphi0) in enumerate(records):
        angle = data.phi if angles is None else angles[i]
        amp = max(float(np.max(np.abs(angle - np.mean(angle)))), 1e-3)
        period = natural_period(linearize(mech, load))
        span = float(data.ts[-1] - data.ts[0])
        omega = 2 * math.pi / (period if period is not None else span)
        ref_phi, ref_dphi = max(amp, abs(phi0)), max(amp * omega, abs(dphi0))
        for n in per_record:
            lg, rf, fd = coordinates(n, float(start[n]), mech, omega_obs, linear, torque)
            names.append(f"{n}[{i}]")
            log.append(lg)
            ref.append(rf)
            fold.append(fd)
        for name, flag, r in (("phi0", state_free[0], ref_phi),
                              ("dphi0", state_free[1], ref_dphi)):
            if flag:
                names.append(f"{name}[{i}]" if multi else name)
                log.append(False)
                ref.append(r)
                fold.append(False)
        outs = data.outputs()
        seg = make_segments(data.ts, np.stack([y for _, y in outs]), n_segments[i], pad)
        exps.append(Experiment(seg, padded_load(load) if pad else load,
                               padded_load(torque) if pad else torque,
                               device_array(phi0, float), device_array(dphi0, float),
                               device_array(ref_phi, float), device_array(ref_dphi, float),
                               *calibration([s for s, _ in outs], sigmas, first_sigma,
                                            mech, ref_dphi / ref_phi)))
    n_global = len(glob)
    glob = glob + list(per_record)  # their start values and structure, as the globals'
    mech_start = mech.replace(**{n: start[n] for n in glob if n in FIELDS})
    # A zero is structure (the compiled program leaves its term out), but a free field
    # that starts at 0 must keep its term, or its sensitivity would be exactly zero.
    nonzero = mech_start.replace(**{n: _TINY for n in glob if n in FIELDS and start[n] == 0})
    structure = Structure.of(mech_start).union(Structure.of(nonzero))
    solver = pick_solver(mech_start, records[0][1], rtol, solver)
    return Problem(mech_start, tuple(exps), device_array(ref), tuple(names), tuple(log),
                   n_global, state_free, solver, structure, jnp.asarray(rtol),
                   jnp.asarray(atol), int(max_steps), adjoint, tuple(fold), per_record, force)


def pick_solver(mech: SliderCrank, load, rtol: float, solver: str, lin=None) -> AbstractSolver:
    """The ODE solver of a fit: the policy's ([`resolve_solver`][]) for the scene's name,
    at the start values, as `simulate` would run it (no save times: a fit's segments have
    their own). `"dopri8-adaptive"` steps its Jacobians' stages in a loop (`loop_stages`):
    a fit calls them tens of times, and compiles them in every process. `lin`: the
    linearisation of `mech` under `load` where the caller has it; else the front door's
    stored one is used (the policy's own traces it in every process)."""
    if lin is None and solver == "auto" and is_concrete((mech, load)):
        lin = linearize(mech, load)
    solver = resolve_solver(solver, mech, rtol, load=load, lin=lin)
    return solver.with_loop_stages() if isinstance(solver, AdaptiveDopri8) else solver
