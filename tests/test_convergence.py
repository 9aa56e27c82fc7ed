"""Issue 38, items 1, 2 and 6: LM's termination judged in the data's units and named
(`termination`), the escalation's end decided by iterations and costs (never wall time),
and a minimum reached from two starts taken as the model's best.

The optimiser tests drive `least_squares` on small residual functions in place of the
compiled program (no ODE solve), so each takes milliseconds."""

import math
import types

import numpy as np
import pytest

from crank_jax.identify import attempt as attempt_module
from crank_jax.identify import escalation as esc_module
from crank_jax.identify import fit as fit_module
from crank_jax.identify import optimize
from crank_jax.identify.fit_options import Method, ShootingMode
from crank_jax.identify.optimize import DECREASE_FRACTION, STEP_FRACTION, least_squares
from crank_jax.identify.outcome import Run
from crank_jax.identify.stages import FitState, Shooting


class _View:
    """A residual view over coordinates named "a" and "b" (identity lift)."""

    problem = types.SimpleNamespace(names=("a", "b"))

    @staticmethod
    def lift(w):
        return np.asarray(w, dtype=float)

    @staticmethod
    def restrict(J, w):
        return J


def _use(monkeypatch, fn):
    """Make `least_squares` evaluate `fn(z) -> (r, J)` instead of the compiled program."""
    def jacobian_at(problem, z):
        r, J = fn(np.asarray(z, dtype=float))
        return np.asarray(r, float), 0, None, np.asarray(J, float)

    monkeypatch.setattr(optimize, "jacobian_at", jacobian_at)


def _misfit_line(z):
    # A straight line fitted to a parabola: the misfit stays 50x the noise level.
    t = np.linspace(-1, 1, 40)
    r = z[0] + z[1] * t - (t + 0.5 * t**2)
    return r, np.stack([np.ones_like(t), t], axis=1)


def test_a_stationary_point_is_converged_in_noise_units(monkeypatch):
    _use(monkeypatch, _misfit_line)
    run = least_squares(_View(), np.array([3.0, -2.0]), 100, 1e-8, "", False,
                        stall_rms=0.03, noise=0.01)
    term = run.termination
    assert run.converged and term["verdict"] == "converged"
    assert term["predicted_decrease"] <= DECREASE_FRACTION
    assert term["largest_step"] <= STEP_FRACTION
    assert term["noise"] == 0.01 and term["words"].startswith("converged: the Gauss-Newton")
    t = np.linspace(-1, 1, 40)
    want = np.linalg.lstsq(_misfit_line(np.zeros(2))[1], t + 0.5 * t**2, rcond=None)[0]
    np.testing.assert_allclose(run.z, want, rtol=1e-9)


def test_a_stall_names_the_combination_it_stalled_along(monkeypatch):
    # The linearisation promises a fall along a + b that the cost never shows (a curved
    # valley's end, as LM crawls): a stall, in noise units, along that direction.
    def fn(z):
        return np.array([1.0, 1.0]), np.array([[1.0, 1.0], [1.0, 1.0]]) * 1e-3

    _use(monkeypatch, fn)
    run = least_squares(_View(), np.array([0.0, 0.0]), 100, 1e-12, "", False,
                        stall_rms=0.3, noise=0.1)
    term = run.termination
    assert term["verdict"] == "stalled" and not run.converged
    assert term["direction"] in ("-0.71 a - 0.71 b", "0.71 a + 0.71 b")
    assert term["words"].startswith(f"stalled along {term['direction']}: the cost fell by 0")
    assert term["predicted_decrease"] == pytest.approx(100.0)  # 0.5 |r|^2 / sigma^2
    assert run.iterations <= optimize.STALL_STEPS + 1


def test_a_spent_budget_says_how_fast_the_cost_still_falls(monkeypatch):
    # exp(-z): LM's every step helps, and the cost falls by orders of sigma^2 per step.
    def fn(z):
        return np.array([np.exp(-z[0]), z[1]]), np.array([[-np.exp(-z[0]), 0.0],
                                                          [0.0, 1.0]])

    _use(monkeypatch, fn)
    run = least_squares(_View(), np.array([-3.0, 0.0]), 5, 1e-12, "", False,
                        stall_rms=3e-4, noise=1e-4)
    term = run.termination
    assert not run.converged and term["verdict"] == "budget"
    assert term["falling_per_iteration"] > 1e3
    assert f"still falling by {term['falling_per_iteration']:.3g} sigma^2" in run.message
    assert term["words"] == "budget spent: " + run.message


def _stub(costs, calls):
    """An `_attempt` that returns converged runs of the given costs, in turn."""
    def attempt(req, plan, shoot, z0, zk, desc):
        calls.append(desc)
        return Run(np.zeros(1), costs[len(calls) - 1], 10, True, "converged")

    return attempt


def _plan_and_request(noise):
    single = types.SimpleNamespace(n_residuals=100)
    # (no segment state: the stubbed basis is over the globals alone)
    shoot = types.SimpleNamespace(names=("a",), log=(True,), folded=(False,),
                                  state_on=np.zeros(0, dtype=bool))
    plan = types.SimpleNamespace(single=single, shoot=shoot, z0=np.zeros(1),
                                 periods=[1.0],
                                 shooting=Shooting("multiple", (2,)), ranges=None)
    req = types.SimpleNamespace(shooting=ShootingMode.AUTO, segments=None, method=Method.LM,
                                multistart=1,
                                seed=0, sigma=None, records=[], known_sigma=None,
                                unit="rad", noise=noise)
    return FitState(req, plan, None, 0, (), plan.shooting)


@pytest.fixture
def stubbed(monkeypatch):
    monkeypatch.setattr(esc_module, "_motion_point", lambda req, plan: None)
    monkeypatch.setattr(attempt_module, "perturb", lambda z, names, log, rng, folded=None: z)
    monkeypatch.setattr(esc_module, "_in_shoot", lambda plan, z: z)
    return monkeypatch


def test_escalation_ends_once_a_second_start_reaches_the_same_minimum(stubbed):
    # Issue 38: on a record the model cannot explain (rms 20x the noise), every start
    # reached the same minimum and the fit still ran 4 more starts (136 iterations where
    # 26 did). A minimum reached from two starts is the model's best: the extra starts
    # stop there.
    calls = []
    noise = 0.01
    cost = 0.5 * 100 * (20 * noise) ** 2
    stubbed.setattr(attempt_module, "attempt", _stub([cost, cost + 0.1 * noise**2, cost,
                                                  cost, cost], calls))
    out = esc_module.optimize_fit(_plan_and_request(noise))
    best, iterations, notes = out.best, out.iterations, out.notes
    assert len(calls) == 2 and iterations == 20
    assert best.cost == cost
    assert any("reached from more than one start" in n for n in notes), notes


def test_escalation_goes_on_while_each_start_finds_a_new_minimum(stubbed):
    calls = []
    noise = 0.01
    costs = [0.5 * 100 * (k * noise) ** 2 for k in (20, 18, 16, 14, 12)]
    stubbed.setattr(attempt_module, "attempt", _stub(costs, calls))
    out = esc_module.optimize_fit(_plan_and_request(noise))
    best, notes = out.best, out.notes
    assert len(calls) == 5 and best.cost == costs[-1]
    assert not any("more than one start" in n for n in notes)


def test_no_clock_is_read_between_the_start_and_the_result(monkeypatch):
    # Item 6: a fit's tries are decided by iterations and costs; the only clock read is
    # for `seconds`. A wall-clock deadline in identify/ would show up here.
    import pathlib

    root = pathlib.Path(fit_module.__file__).parent
    for path in root.glob("*.py"):
        text = path.read_text()
        for word in ("monotonic(", "deadline", "time.time(", "process_time("):
            assert word not in text, (path.name, word)
    fit_text = (root / "fit.py").read_text()
    assert fit_text.count("perf_counter()") == 2  # `seconds`: the start and the result
    assert math.isfinite(optimize.STALL_DECREASE)


def test_where_minpack_can_go_no_further_a_tiny_promise_is_convergence(monkeypatch):
    # The slide-only rig's polish (experiments/misfit_rig.py): MINPACK found no step
    # that lowered the cost, with 1.3e-4 sigma^2 left on the linearisation's promise,
    # and the fit reported "stalled", not converged, at its best point.
    def fn(z):
        # A minimum at 0 whose Jacobian is off by a hair (the solve's rounding): the
        # linearisation promises 4.5e-4 sigma^2 that no step can give.
        r = np.array([z[0], z[1], 3.0])
        J = np.array([[1.0, 0.0], [0.0, 1.0], [0.01, 0.0]])
        return r, J

    _use(monkeypatch, fn)
    run = least_squares(_View(), np.array([0.0, 0.0]), 100, 1e-12, "", False,
                        stall_rms=3.0, noise=1.0)
    term = run.termination
    assert run.converged and term["verdict"] == "converged", term
    assert term["words"].startswith("converged: no further progress at machine precision")
    assert DECREASE_FRACTION < term["predicted_decrease"] <= optimize.STALL_DECREASE


def test_a_polished_run_takes_the_polish_verdict(stubbed):
    # The slide-only rig (issue 38's second row): multiple shooting stalled on its
    # continuity defects, its single-shooting polish converged at the best cost seen,
    # and the fit said "NOT converged" because the first stage had not.
    stages = [Run(np.zeros(2), 1.0, 30, False, "stalled: ..."),
              Run(np.zeros(2), 0.5, 7, True, "converged",
                  {"verdict": "converged", "words": "converged: ..."})]
    stubbed.setattr(attempt_module, "guarded", lambda *args: stages.pop(0))
    stubbed.setattr(attempt_module, "recoordinate", lambda src, dst, z: np.asarray(z)[:2])
    stubbed.setattr(attempt_module, "recoordinate_basis", lambda *args: np.eye(2))
    stubbed.setattr(attempt_module, "Subspace", lambda *args: None)
    stubbed.setattr(attempt_module, "InValues", _Shifted)
    state = _plan_and_request(0.01)
    plan, req = state.plan, state.req
    plan.Bg, req.tol, req.max_steps, req.progress = np.eye(2), 1e-8, 100, False
    run = attempt_module.attempt(req, plan, plan.shoot, np.zeros(2), np.zeros(2), "fit")
    assert run.converged and run.message == "converged" and run.iterations == 37
    assert run.termination["verdict"] == "converged" and run.cost == 0.5


class _Shifted:
    """A stand-in for `InValues`: the point `z + B w`, nothing in log space."""

    def __init__(self, problem, z, B):
        self.z, self.B = np.asarray(z, float), np.asarray(B, float)

    def lift(self, w):
        return self.z + self.B @ np.asarray(w, float)


def _at_the_bound(stubbed, grad_sign):
    """`attempt.off_the_bound` on a stalled run with coordinate 0 (a folded friction) at
    0, its held and released runs stubbed; the gradient into the feasible side has the
    sign `grad_sign`. **Returns:** (the run reported, the descriptions of the runs)."""
    calls = []
    runs = {"held": Run(np.zeros(2), 4.0, 20, True, "converged"),
            "released": Run(np.zeros(2), 3.0, 30, True, "converged")}

    def guarded(fn, view, w0, *args):
        desc = args[-2]
        calls.append(desc)
        return runs["held" if "held" in desc else "released"]._replace(z=np.zeros(len(w0)))

    def jacobian_at(problem, z):
        J = np.array([[1.0, 0.5], [0.0, 1.0]])
        r = np.array([grad_sign * 2.0, 0.0])  # J[:, 0] @ r = 2 grad_sign
        return r, 0, None, J

    stubbed.setattr(attempt_module, "guarded", guarded)
    stubbed.setattr(attempt_module, "jacobian_at", jacobian_at)
    stubbed.setattr(attempt_module, "InValues", _Shifted)
    state = _plan_and_request(0.01)
    plan, req = state.plan, state.req
    plan.single = types.SimpleNamespace(p=2, n_global=2, folded=(True, False))
    plan.Bg, req.tol, req.max_steps, req.progress = np.eye(2), 1e-8, 100, False
    stalled = Run(np.array([1e-7, 0.3]), 5.0, 60, False, "stalled: ...")
    return attempt_module.off_the_bound(req, plan, stalled, "fit"), calls


def test_a_run_stalled_with_a_friction_at_its_bound_is_finished_off_it(stubbed):
    # Issue 38, the friction stand-in (experiments/misfit_rig.py): LM stalled with the
    # guide friction F_s at its bound 0 (the kink of `ref |z|`), at rms 0.0916 rad, where
    # the best fit, F_s = 0.62, has 0.09146. Held at 0 while the others finish, then
    # released where the cost falls into F_s > 0, the fit ends at the best minimum.
    run, calls = _at_the_bound(stubbed, -1.0)
    assert calls == ["fit (friction held at 0)", "fit (friction released)"]
    assert run.converged and run.cost == 3.0 and run.iterations == 60 + 20 + 30
    assert run.z[0] == pytest.approx(2.0 / 1.0)  # released from its 1-D Gauss-Newton step


def test_a_friction_whose_cost_rises_off_its_bound_stays_there(stubbed):
    # The gradient points out of the feasible side: the point on the bound, with the
    # others finished, is a constrained minimum; nothing is released.
    run, calls = _at_the_bound(stubbed, 1.0)
    assert calls == ["fit (friction held at 0)"]
    assert run.converged and run.cost == 4.0 and run.iterations == 80 and run.z[0] == 0.0


def test_value_coordinates_map_onto_log_ones_by_the_chain_rule():
    # `InValues`: the polish's view, linear in each value where the problem holds some in
    # log space. Its lift and its sensitivities must agree (the Gauss-Newton test and the
    # standard errors use both), and a value stepped to or below 0 is outside.
    from crank_jax.identify.programs import InValues

    problem = types.SimpleNamespace(log=(True, False), folded=(False, True))
    z0 = np.array([math.log(2.0), 0.5])
    B = np.array([[0.6, 0.8], [0.8, -0.6]])
    view = InValues(problem, z0, B)
    np.testing.assert_allclose(view.lift(np.zeros(2)), z0, rtol=1e-15)
    w = np.array([0.3, -0.2])
    u = np.array([1.0, 0.5]) + view.B @ w  # values over the start's, and z1 itself
    np.testing.assert_allclose(view.lift(w), [math.log(2.0 * u[0]), u[1]], rtol=1e-14)
    h = 1e-6
    fd = np.stack([(view.lift(w + h * e) - view.lift(w - h * e)) / (2 * h)
                   for e in np.eye(2)], axis=1)
    np.testing.assert_allclose(view.restrict(np.eye(2), w), fd, rtol=1e-8, atol=1e-10)
    J = np.array([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]])
    np.testing.assert_allclose(view.restrict(J, w), J @ fd, rtol=1e-8)
    far = -2.0 / view.B[0, 0] * np.array([1.0, 0.0])  # u0 = 1 + B[0, 0] w0 = -1
    assert np.isnan(view.lift(far)[0])


def test_lm_in_value_coordinates_rejects_a_point_outside_without_solving_it(monkeypatch):
    # The residuals want the value e^z at -1; in value coordinates LM's step lands below
    # 0, where no solve may run: that point is a failed one, rejected, and the run ends at
    # a positive value.
    from crank_jax.identify.programs import InValues

    seen = []

    def fn(z):
        seen.append(np.array(z))
        v = np.exp(z[0])
        return np.array([v + 1.0]), np.array([[v]])

    _use(monkeypatch, fn)
    problem = types.SimpleNamespace(log=(True,), folded=(False,), names=("a",))
    view = InValues(problem, np.array([0.0]), np.eye(1))
    run = least_squares(view, np.zeros(1), 30, 1e-10, "", False)
    assert seen and all(np.all(np.isfinite(z)) for z in seen)
    assert np.isfinite(run.cost) and np.exp(view.lift(run.z)[0]) > 0


class _Folded(_View):
    """A view over "a" (folded: value |z|) and "b"."""

    problem = types.SimpleNamespace(names=("a", "b"), folded=(True, False))


def _kink(z):
    # The value |z0| wants to be -1: its best is the bound 0, a kink in z0.
    s = 1.0 if z[0] >= 0 else -1.0
    return (np.array([abs(z[0]) + 1.0, z[1] - 1.0, 0.1 * z[1]]),
            np.array([[s, 0.0], [0.0, 1.0], [0.0, 0.1]]))


def test_a_run_sitting_on_a_folded_bound_stops_there_for_the_caller(monkeypatch):
    # Issue 38, the friction stand-in: LM crawled 30-100 iterations at the kink of a
    # folded friction at 0. With `at_bounds` it stops after BOUND_STEPS iterations there,
    # naming the parameter, for `attempt.off_the_bound` to hold it at 0.
    _use(monkeypatch, _kink)
    run = least_squares(_Folded(), np.array([0.5, 0.0]), 100, 1e-12, "", False,
                        stall_rms=0.3, noise=0.1, at_bounds=True)
    term = run.termination
    assert not run.converged and term["verdict"] == "stalled"
    assert term["direction"] == "a at its bound 0" and run.message == "stalled at the bound a = 0"
    assert abs(run.z[0]) < 1e-3
    # Without it, the same run is not stopped that way.
    plain = least_squares(_Folded(), np.array([0.5, 0.0]), 100, 1e-12, "", False,
                          stall_rms=0.3, noise=0.1)
    assert plain.termination["direction"] != "a at its bound 0"


def test_a_coordinate_held_by_the_view_is_not_a_bound_stall(monkeypatch):
    # The run held at the bound (`off_the_bound`) holds the friction at 0 on purpose: its
    # view cannot move it, and that is no reason to stop.
    _use(monkeypatch, _kink)

    class Held(_Folded):
        @staticmethod
        def lift(w):
            return np.array([0.0, float(np.asarray(w)[0])])

        @staticmethod
        def restrict(J, w):
            return np.asarray(J)[:, 1:]

    run = least_squares(Held(), np.array([0.0]), 100, 1e-12, "", False,
                        stall_rms=0.3, noise=0.1, at_bounds=True)
    assert run.termination["direction"] != "a at its bound 0"
    assert run.z[0] == pytest.approx(1.0 / 1.01, rel=1e-6)


def _sliding(a):
    """A residual the linearisation overrates: J promises the first residual `a` away in
    one step, the cost gives a hundredth of it, step after step (LM at rest)."""
    def fn(z):
        return (np.array([a * (1.0 - 1e-2 * np.tanh(z[0])), 1.0]),
                np.array([[-a], [0.0]]))
    return fn


class _One(_View):
    problem = types.SimpleNamespace(names=("a",))


@pytest.mark.parametrize("a, converged", [(0.01, True), (0.05, False)])
def test_a_stall_with_nothing_left_to_gain_is_convergence(monkeypatch, a, converged):
    # Issue 38, the friction stand-in: the run released from the bound ended at the best
    # minimum "stalled" (the cost fell 0.0099 sigma^2 over 8 iterations, the Gauss-Newton
    # step predicting 1.4e-4 sigma^2 more), and the fit reported a worse converged point.
    # At rest with a promise below the stall test's own size (0.01 sigma^2) the run has
    # converged; with more (here 0.125 sigma^2) it has stalled.
    _use(monkeypatch, _sliding(a))
    run = least_squares(_One(), np.zeros(1), 100, 1e-14, "", False, stall_rms=0.3,
                        noise=0.1)
    term = run.termination
    assert run.converged is converged
    # (the first residual, a (1 - 0.01 tanh z), has moved by under 2%)
    assert term["predicted_decrease"] == pytest.approx(0.5 * (a / 0.1) ** 2, rel=0.04)
    if converged:
        assert term["verdict"] == "converged" and term["words"].startswith(
            "converged: the cost fell by")
    else:
        assert term["verdict"] == "stalled"


def test_the_optax_method_reaches_a_least_squares_minimum(monkeypatch):
    # `method="optax"` (Adam, then L-BFGS) on a linear least-squares problem in place of
    # the compiled ODE residuals: it ends at the normal equations' solution, converged.
    # (The end-to-end smoke on the pendulum, 74 s of compiling, is in the full tier.)
    import equinox as eqx
    import jax.numpy as jnp

    from crank_jax.identify import optax_fit

    class Line(eqx.Module):
        t: jnp.ndarray
        y: jnp.ndarray

        def residuals(self, z):
            return z[0] + z[1] * self.t - self.y, 0, 0

    t = jnp.linspace(-1.0, 1.0, 30)
    line = Line(t, 0.3 - 1.2 * t + 0.05 * jnp.sin(7.0 * t))

    def evaluate(model, z):
        r = np.asarray(model.residuals(jnp.asarray(z))[0])
        return 0.5 * float(r @ r), 0

    monkeypatch.setattr(optax_fit, "evaluate", evaluate)
    run = optax_fit.minimize_optax(line, np.zeros(2), 400, 1e-12, "", False)
    A = np.stack([np.ones(30), np.asarray(t)], axis=1)
    want = np.linalg.lstsq(A, np.asarray(line.y), rcond=None)[0]
    assert run.converged and run.iterations < 400
    np.testing.assert_allclose(run.z, want, atol=1e-6)
