"""The solver policy: the one place that turns `"auto"` and solver names into a solver.

`simulate`, `fit` and `sweep` all call [`resolve_solver`][], so a scene gets the same
solver whichever of them runs it. The rule, in order:

It returns a solver object (`solvers.py`, made once per name by `names.py`'s table).

1. A solver object, or a name other than `"auto"`, is taken as given (after checking the
   name is known).
2. Stiff (see [`choose_solver`][]): `"kvaerno5"`, an L-stable ESDIRK.
3. Otherwise, with no sampled load, `"dopri8-adaptive"`: adaptive fused Dopri8 steps with
   dense output (`adaptive.py`), a `vmap`-ed batch in lockstep (`lockstep.py`), for
   concrete and traced parameters, any save times. It is the fastest of the library's
   solvers at equal error (experiments/bench_work_precision.py,
   experiments/bench_throughput.py). With a sampled load, `"dopri8"` below
   `rtol = 1e-7` and `"tsit5"` above (diffrax's, whose steps end at the load's knots).
   Sweeps ask for batch-invariant results (`batch_invariant=True`) and keep the per-member
   `"dopri8-uniform"` on uniform save times.

A concrete `simulate` call also takes its host-side plan from here ([`host_plan`][]: its
input checks, the linearisation, the structure and the solver); the front door
(`crank_jax/simulation.py`) keeps plans for repeated calls with the same inputs.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import numpy as np

from ..model.linear import linearize
from ..model.loads import AbstractLoad, is_sampled
from ..model.params import FIELDS, SliderCrank, validation_rules
from ..model.structure import Structure
from .inputs import check_tolerances, check_unbatched
from .names import SOLVERS, solver_named
from .solvers import AbstractSolver
from .uniform import uniform_grid

__all__ = ["SOLVERS", "choose_solver", "fastest_mode", "resolve_solver", "check_solver",
           "is_concrete", "check_time_scale", "check_travel", "host_plan", "HostPlan"]


# How many times its stability floor the fused uniform solver may need per interval to
# resolve a fast mode at the default tolerance (a margin, not a tuned constant: below it
# the adaptive diffrax path is used).
_UNIFORM_MARGIN = 8.0

# The "auto" switch to an implicit solver (see `choose_solver`). Measured on the lab rig
# (experiments/stress_stiffness.py): at the stability limit an explicit Tsit5 takes about
# 0.75 steps per radian of the fast mode, Kvaerno5 resolves a decaying oscillation at about
# 8 steps per radian while it is above the tolerance, and one Kvaerno5 step costs about
# 13 Tsit5 steps. Implicit wins once the fast mode has decayed within 1/140 of the span.
_SWITCH_RATIO = 140.0
# |h rate| an explicit solver can take on the fastest mode (Dopri8's stability region
# reaches ~4.8 along the imaginary axis, Tsit5's ~3.5): below span * rate / this, no
# explicit solve can finish.
_EXPLICIT_H_RATE = 3.5
# A mode this many times faster than the span is below float64's resolution of the times:
# a units mistake, whatever the solver.
_MAX_SPAN_RATE = 1e12
# No explicit or implicit step resolves a turn of the crank (2 pi of the geometry's
# period) in fewer steps than this.
_MIN_STEPS_PER_TURN = 4.0
# A real fast mode is stiff only if the other mode is this much slower (otherwise the
# slow mode, e.g. a crank falling over, needs the same small steps).
_STIFFNESS_RATIO = 1e2


def is_concrete(tree) -> bool:
    """True if no leaf of `tree` is a tracer (the values can be read on the host)."""
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(tree))


def check_solver(name: str) -> str:
    """`name` if it is in [`SOLVERS`][], else a `ValueError` naming the choices."""
    if name not in SOLVERS:
        raise ValueError(f"unknown solver {name!r}; choose from {list(SOLVERS)}")
    return name


def fastest_mode(lin) -> tuple[np.ndarray, np.ndarray]:
    """The fastest mode of the linearisation `mu s^2 + chi s + xi = 0` (host NumPy).

    **Arguments:** `lin`, a [`Linearization`][] (any batch shape).

    **Returns:** `(rate, decay)`, arrays of the batch shape, 1/s: `rate = |s_fast|`, the
    largest eigenvalue magnitude (it bounds an explicit solver's step by stability), and
    `decay = -Re(s_fast)`, how fast that mode dies out (<= 0: it does not).
    """
    mu, chi, xi = (np.asarray(x, dtype=float) for x in (lin.mu, lin.chi, lin.xi))
    disc = chi**2 - 4 * mu * xi
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        root = np.sqrt(np.abs(disc))
        real = disc >= 0
        # Real roots (-chi -+ root)/(2 mu): with chi >= 0 the "-" root is the larger.
        rate = np.where(real, (chi + root) / (2 * mu), np.sqrt(np.abs(xi) / mu))
        decay = np.where(real, (chi + root) / (2 * mu), chi / (2 * mu))
    return rate, decay


def _slowest_rate(lin) -> np.ndarray:
    mu, chi, xi = (np.asarray(x, dtype=float) for x in (lin.mu, lin.chi, lin.xi))
    disc = chi**2 - 4 * mu * xi
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        root = np.sqrt(np.abs(disc))
        # A complex pair has one modulus; the slow dynamics is then the forcing's.
        return np.where(disc >= 0, np.abs(-chi + root) / (2 * mu), 0.0)


def choose_solver(
    mech: SliderCrank, rtol: float, load: AbstractLoad | None = None, *,
    span: float = 10.0, lin=None,
) -> str:
    """The solver that `solver="auto"` picks, from the tolerance and the stiffness.

    Stiff means: an explicit solver's step is limited by stability on a fast mode that
    no longer matters. With `rate`, `decay` = [`fastest_mode`][] of the linearisation
    (with the slider force's mean), the switch is

        ln(1/rtol) / decay  <  span / 140

    (the fast mode falls below the tolerance within 1/140 of the span), and, for a real
    fast mode, the other mode is more than 100x slower. Then `"kvaerno5"`, an L-stable
    ESDIRK, steps over the decayed fast mode. The constants are measured (see the README's
    stability section): an oscillating fast mode with damping ratio 0.05 over 2 s switches
    at k ~ 1e6 N*m/rad on the lab rig, where Tsit5 needs ~4e4 steps and Kvaerno5 ~3.4e3.
    An undamped fast mode never switches: it must be resolved, and an explicit solver
    resolves it cheapest. Otherwise `"dopri8"` for `rtol < 1e-7` (8th order wins at tight
    tolerances) and `"tsit5"` above.

    **Arguments:** `mech` (a batch counts as stiff if any member is); `rtol`; `load`, the
    slider force; `span`, the integration time, s.

    **Returns:** a name from [`SOLVERS`][]. Needs concrete parameters; traced ones (inside
    `jit`) skip the stiffness test.
    """
    concrete = is_concrete(mech) and is_concrete(load)
    if concrete and lin is None:
        lin = linearize(mech, load)
    return _choose(lin if concrete else None, rtol, span)


def _choose(lin, rtol: float, span: float) -> str:
    """[`choose_solver`][] from `lin`, the linearisation of concrete parameters and loads
    (None for traced ones: no stiffness test)."""
    if lin is not None:
        rate, decay = fastest_mode(lin)
        slow = _slowest_rate(lin)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            decays_early = decay * float(span) > _SWITCH_RATIO * np.log(1 / float(rtol))
            separated = (slow * _STIFFNESS_RATIO < rate) | (slow == 0)
        if np.any(decays_early & separated):
            return "kvaerno5"
    return "dopri8" if float(rtol) < 1e-7 else "tsit5"


def resolve_solver(
    solver: str | AbstractSolver, mech: SliderCrank, rtol, atol=None, *,
    load: AbstractLoad | None = None, torque: AbstractLoad | None = None, ts=None,
    max_steps: int | None = None, batch_invariant: bool = False, lin=None,
) -> AbstractSolver:
    """The solver that runs: `solver` itself, or for `"auto"` the choice described in the
    module docstring.

    **Arguments:** `solver`, a name from [`SOLVERS`][] or a solver object; `mech` (a batch
    counts as stiff if any member is); `rtol`, `atol` (arrays or floats; traced ones count
    as the defaults); `load`, `torque`; `ts`, the save times (n,) if known on the host;
    `max_steps`, the caller's step budget (the fused solver splits it evenly over the save
    intervals);
    `lin`, the linearisation of concrete `mech`, `load` if the caller has it;
    `batch_invariant`: each member of a `vmap`-ed batch must get exactly the result of its
    own solve, whatever else is in the batch (a sweep's results do not depend on its
    chunking or order). `"dopri8-adaptive"` steps a batch in lockstep, so then
    `"dopri8-uniform"` is chosen where it applies (uniform save times known on the host,
    its step budget, no Coulomb friction; its steps are per member), else diffrax's.

    **Returns:** the solver object (`names.solver_named` of the name chosen; its name is
    `names.name_of(solver)`).
    """
    if isinstance(solver, AbstractSolver):
        return solver
    name = _resolve_name(check_solver(solver), mech, rtol, load, torque, ts, max_steps,
                         batch_invariant, lin)
    return solver_named(name)


def _resolve_name(solver, mech, rtol, load, torque, ts, max_steps, batch_invariant,
                  lin) -> str:
    """[`resolve_solver`][] on names: the table's name that runs."""
    if solver != "auto":
        return solver
    # The span on the host (NumPy): under a user's `jit`, even indexing a concrete `ts`
    # would be staged out as a tracer.
    concrete_ts = ts is not None and is_concrete(ts)
    span = float(np.ptp(np.asarray(ts))) if concrete_ts else 10.0
    rtol_host = float(np.max(np.asarray(rtol))) if is_concrete(rtol) else 1e-8
    if not (is_concrete(mech) and is_concrete(load)):
        lin = None  # traced values: no stiffness test, no interval budget
    elif lin is None:
        lin = linearize(mech, load)  # once, for the stiffness test and the interval budget
    name = _choose(lin, rtol_host, span)
    sampled = any(is_sampled(x) for x in (load, torque))
    if batch_invariant:
        if (name in ("tsit5", "dopri8") and concrete_ts and not sampled
                and uniform_grid(np.asarray(ts))
                and _fits_interval_budget(lin, np.asarray(ts), max_steps)
                and not _has_coulomb(mech)):
            name = "dopri8-uniform"
        return name
    if name != "kvaerno5" and not sampled:
        # Traced parameters too (a `vmap`-ed batch, `jacfwd`): that is how users batch and
        # differentiate, and the fused solver is the fastest there as well. Not across a
        # sampled load's kinks, where diffrax's steps end at the knots.
        name = "dopri8-adaptive"
    return name


def _has_coulomb(mech) -> bool:
    """Concrete Coulomb friction (T_c or F_s nonzero): its tanh is nearly a kink at rest,
    which the fused solver's summed per-interval error control handles badly (measured: the
    lab rig with T_c = 0.004 N*m exhausts its step budget where adaptive Dopri8 takes 1843
    steps), so the adaptive path runs it. Traced values cannot be read and keep the fused
    solver."""
    names = [n for n in ("T_c", "F_s") if hasattr(mech, n)]
    vals = [getattr(mech, n) for n in names]
    return is_concrete(vals) and any(bool(np.any(np.asarray(v) != 0)) for v in vals)


def _fits_interval_budget(lin, ts: np.ndarray, max_steps: int | None) -> bool:
    """Whether the fused uniform solver can afford the fastest mode: it takes at least
    `dt * rate / 3` steps in every save interval (Dopri8's stability on that mode) and
    several times that to resolve it, out of `max_steps / (n - 1)` per interval. A fast
    shaft mode that an adaptive solver resolves once and then steps over at its stability
    limit would exhaust it (measured: a sweep to k = 1e7 on the lab rig). `lin`: the
    linearisation of concrete parameters, or None for traced ones (then True)."""
    if max_steps is None or lin is None:
        return True
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        rate, _ = fastest_mode(lin)
        rate = np.asarray(rate, dtype=float)
        top = float(np.max(np.where(np.isfinite(rate), rate, 0.0))) if rate.size else 0.0
    dt = float(np.max(np.diff(ts)))
    per_interval = max(1, int(max_steps) // max(ts.shape[0] - 1, 1))
    return _UNIFORM_MARGIN * dt * top / _EXPLICIT_H_RATE <= per_interval


def check_time_scale(lin, solver: AbstractSolver, span: float, max_steps: int
                     ) -> float | None:
    """`ValueError` if the fastest mode of `lin`, the linearisation of concrete parameters
    and loads, cannot be integrated over `span`; else the fastest rate, 1/s, for
    [`check_travel`][]; None where `lin` is None (traced values: not checked).

    An explicit solver needs at least `span * rate / 3.5` steps (its stability limit on the
    fastest mode, `rate` from [`fastest_mode`][]); more than `max_steps` means the solve can
    only fail. Any solver fails once `span * rate > 1e12` (or the rate overflows). Both
    happen when k, a mass or an inertia is off by orders of magnitude (k = 1e300, masses of
    1e-300), so the message names the rate and the linearisation and asks to check them.
    """
    if lin is None:
        return None
    rate, _ = fastest_mode(lin)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        rate = np.asarray(rate, dtype=float)
        top = float(np.max(np.where(np.isnan(rate), 0.0, rate))) if rate.size else 0.0
        product = top * float(span)
        explicit = not solver.implicit
        need = product / _EXPLICIT_H_RATE
    if not (np.isfinite(product) and product <= _MAX_SPAN_RATE
            and not (explicit and need > max_steps)):
        mu, chi, xi = (float(np.max(np.abs(np.asarray(x, dtype=float)))) for x in
                       (lin.mu, lin.chi, lin.xi))
        raise ValueError(
            f"the fastest mode of the linearized crank is {top:.3g} rad/s (mu = {mu:.3g} "
            f"kg*m^2, chi = {chi:.3g} N*m*s/rad, xi = {xi:.3g} N*m/rad): over {span:g} s "
            f"that needs ~{need:.3g} solver steps (max_steps = {max_steps}); check the units "
            f"and values of k, c and the masses and inertias")
    return top


def check_travel(lin, top: float, phi0, dphi0, span: float, max_steps: int) -> None:
    """`ValueError` if the initial state is so far from rest that the crank must turn more
    times than `max_steps` can resolve (phi0 = 1e300 rad: the spring winds the crank back
    through every one of those turns).

    The crank travels at least `A = |phi0 - phi_eq| + |dphi0| / omega` (omega: the fastest
    linear mode `top`, or 1/span without one) once it moves for a time `1/omega`, and every
    turn needs at least `_MIN_STEPS_PER_TURN` steps.
    """
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        eq = np.nan_to_num(np.asarray(lin.phi_eq, dtype=float))
        omega = top if np.isfinite(top) and top * span >= 1 else 1.0 / span
        amp = float(np.max(np.abs(float(phi0) - eq))) + abs(float(dphi0)) / omega
        need = amp / (2 * np.pi) * _MIN_STEPS_PER_TURN
    if np.isfinite(need) and need <= max_steps:
        return
    raise ValueError(
        f"the initial state phi0 = {float(phi0):.3g} rad, dphi0 = {float(dphi0):.3g} rad/s "
        f"is ~{amp / (2 * np.pi):.3g} turns from rest: resolving them needs more than "
        f"max_steps = {max_steps} solver steps; start within a few turns of the "
        f"equilibrium (phi is in radians, and the spring k is not periodic in it)")


class HostPlan(NamedTuple):
    """What [`host_plan`][] decides for a concrete `simulate` call."""

    solver: AbstractSolver  #: the solver that runs
    structure: Structure  #: the static set of terms
    lin: object  #: the `Linearization` of concrete parameters and loads, else None
    top: float | None  #: its fastest rate, 1/s, where the time scale was checked, else None
    span: float | None  #: `ts[-1] - ts[0]`, s, likewise (both for [`check_travel`][])
    invalid: str | None  #: the first failed parameter check's message, or None


def host_plan(mech, load, torque, ts, rtol, atol, solver, max_steps, throw, structure, *,
              linearize=linearize) -> HostPlan:
    """The host-side part of a `simulate` call that depends on neither the initial state
    nor the user's force: input checks, the linearisation, the structure, the solver.
    `simulate` raises `invalid` when every input is concrete, checks the initial state with
    [`check_travel`][] where `top` is set, and keeps plans for repeated calls (its memo is
    the front door's, not the core's). `linearize`: the linearisation to use (default the
    model's; the front door passes its stored program)."""
    if is_concrete(ts):
        d = np.diff(np.asarray(ts))
        if not np.all(d > 0):
            i = int(np.argmin(d)) + 1
            raise ValueError(f"ts must increase strictly; it does not at index {i}")
    check_tolerances(rtol, atol)
    check_unbatched("SliderCrank", mech)
    # Concrete parameters are read on the host once (np.asarray per leaf: 5x cheaper than
    # `jax.device_get` on the CPU), and linearised once where the solver policy or the
    # time-scale check needs it.
    concrete = is_concrete(mech)
    host_mech = jax.tree_util.tree_map(np.asarray, mech) if concrete else mech
    checked = throw and is_concrete(ts)
    lin = (linearize(mech, load) if concrete and is_concrete(load)
           and (solver == "auto" or checked) else None)
    if structure is None:
        structure = Structure.of(host_mech if concrete else mech)
    solver = resolve_solver(solver, host_mech, rtol, atol, load=load, torque=torque, ts=ts,
                            max_steps=max_steps, lin=lin)
    top = span = None
    if checked:
        span = float(np.ptp(np.asarray(ts)))
        top = check_time_scale(lin, solver, span, int(max_steps))
    invalid = _invalid_parameter(host_mech) if concrete else None
    return HostPlan(solver, structure, lin, top, span, invalid)


def _invalid_parameter(mech: SliderCrank) -> str | None:
    """The message of the first parameter check that concrete `mech` fails (the checks
    `_solve` makes with `eqx.error_if`, same messages), or None."""
    # Python floats: the parameters are scalars here (`check_unbatched`), and the ~45
    # comparisons run ~10x faster on floats than on 0-d arrays.
    values = {n: float(getattr(mech, n)) for n in FIELDS}
    for name, bad, rule in validation_rules(values):
        if bad:
            return f"SliderCrank.{name} is invalid: {rule}."
    return None
