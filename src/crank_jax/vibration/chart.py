"""Parametric-resonance charts: the stability of the rest position phi = 0 (or pi, where a
crank hangs) under a harmonic slider force `P(t) = P0 + P1 cos(2 pi f t)`, over a grid of
`(P1, f)`.

At the dead centre (no offset, gravity along the slider line, no crank torque) phi = 0 is an
equilibrium for any P(t), and the slider force enters the linearised equation as a
stiffness, `mu phi'' + chi phi' + (xi0 + xi_P P(t)) phi = 0` (DESIGN.md section 8): a
damped Mathieu equation. Its Floquet multipliers (of the full nonlinear flow's Jacobian at
rest over one period, `floquet.py`) leave the unit circle inside tongues near
`f = 2 f_n / n`. [`mathieu_tongue`][] gives the first tongue's edges from first-order
harmonic balance, the reference for small forcing.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..model.dynamics import CrankField, Structure
from ..model.loads import ConstantLoad, HarmonicLoad, NoLoad
from ..simulation import linearize
from .drive import VibrationError, as_range, check_scene, check_smooth
from .floquet import monodromy_at_rest, multipliers
from .rest import rest_rate

__all__ = ["Chart", "stability_chart", "floquet_max", "mathieu_tongue", "MAX_GRID"]

#: The largest grid side: N^2 monodromy matrices in one batch (memory and time).
MAX_GRID = 400


class Chart(NamedTuple):
    """A stability chart: `freq_hz` (N,), `amplitude` (N,) P1 values (N), `floquet_max`
    (N, N) the largest multiplier modulus, one row per amplitude (NaN where its solve
    failed), `stable` (N, N) bool, `ok` (N, N) bool: the point was computed (a failed point
    is neither stable nor unstable), and `rest`, the rest angle analysed (0 or pi, rad)."""

    freq_hz: np.ndarray
    amplitude: np.ndarray
    floquet_max: np.ndarray
    stable: np.ndarray
    ok: np.ndarray | None = None
    rest: float = 0.0

    @property
    def unstable(self) -> np.ndarray:
        """(N, N) bool: computed and unstable (`~stable` also holds the failed points)."""
        ok = np.isfinite(self.floquet_max) if self.ok is None else np.asarray(self.ok)
        return ok & ~np.asarray(self.stable)

    def to_dict(self) -> dict:
        return {k: np.asarray(v).tolist() for k, v in self._asdict().items()}


def _mean_P(scene):
    load = scene.load
    if isinstance(load, NoLoad):
        return jnp.asarray(0.0)
    if isinstance(load, (ConstantLoad, HarmonicLoad)):
        return load.mean()
    raise VibrationError("a stability chart needs the scene's [load] to be absent, constant "
                         "(P0) or harmonic (P0, P1, freq_hz): its P1 and frequency are the "
                         "chart's axes")


def check_chart_scene(scene) -> None:
    """Refuse scenes whose rest position is not phi = 0 for every P(t)."""
    m = scene.mech
    if float(np.asarray(m.e)) != 0:
        raise VibrationError(f"a stability chart needs the slider line through the crank "
                             f"axis: set e = 0 (got e = {float(np.asarray(m.e)):g} m, which "
                             "moves the rest position with P)")
    if float(np.asarray(m.gravity_angle)) != 0 and float(np.asarray(m.g)) != 0:
        raise VibrationError("a stability chart needs gravity along the slider line: set "
                             "gravity_angle = 0 (or g = 0); otherwise phi = 0 is not at rest")
    if not isinstance(scene.torque, NoLoad):
        raise VibrationError("a stability chart is of the rest position under P(t) alone: "
                             "remove the scene's [torque] table")
    check_smooth(m, "a stability chart (the linearization at rest)")
    _mean_P(scene)


def floquet_max(scene, amplitude, freq_hz, *, structure: Structure | None = None,
                rest=0.0):
    """The largest Floquet multiplier modulus of the rest `phi = rest` (0 or pi, rad) under
    `P0 + amplitude cos(2 pi freq_hz t)` (N, Hz); `P0` is the scene's mean slider force.
    NaN where the solve failed. Traceable, vmappable."""
    load = HarmonicLoad(_mean_P(scene), amplitude, freq_hz, jnp.pi / 2)
    field = CrankField(scene.mech, load, NoLoad(), structure or Structure())
    y0 = jnp.stack([jnp.asarray(rest, float), 0.0])
    lam = multipliers(monodromy_at_rest(field, y0, 1.0 / jnp.asarray(freq_hz, float),
                                rtol=scene.rtol, atol=scene.atol))
    return jnp.abs(lam[0])


def stability_chart(scene, load_amplitude: tuple[float, float], freq_hz: tuple[float, float],
                    grid: int = 40) -> Chart:
    """The largest Floquet multiplier of the rest position over a grid of slider-force
    amplitudes and frequencies.

    **Arguments:** `scene` (no offset, no crank torque, no Coulomb friction; its mean P0
    is kept, its rtol/atol are the solver's); `load_amplitude`, `(P1_lo, P1_hi)`, N, >= 0;
    `freq_hz`, `(f0, f1)`, Hz, > 0; `grid`, N points on each axis (2..`MAX_GRID`).

    **Returns:** a [`Chart`][]; `stable` is `floquet_max < 1`. One compiled batch of N^2
    monodromy matrices (each a forward-mode solve over one period).
    """
    check_chart_scene(scene)
    check_scene(scene, "stability_chart")
    a0, a1 = as_range("load_amplitude", load_amplitude, "N", zero_ok=True)
    f0, f1 = as_range("freq_hz", freq_hz, "Hz")
    if isinstance(grid, bool) or not (isinstance(grid, int) and 2 <= grid <= MAX_GRID):
        raise VibrationError(f"grid must be an integer from 2 to {MAX_GRID}, got {grid!r}")
    rest = chart_rest(scene)
    amps, freqs = np.linspace(a0, a1, grid), np.linspace(f0, f1, grid)
    A, F = np.meshgrid(amps, freqs, indexing="ij")
    fm = np.asarray(_chart(scene, jnp.asarray(A.ravel()), jnp.asarray(F.ravel()),
                           Structure.of(scene.mech), rest)).reshape(grid, grid)
    ok = np.isfinite(fm)
    return Chart(freqs, amps, fm, ok & (fm < 1.0), ok, rest)


def chart_rest(scene) -> float:
    """The rest a chart analyses, rad: phi = 0, or pi where only pi is statically stable
    under the mean slider force (a crank hanging from its axis). Both are equilibria for
    any P(t) under [`check_chart_scene`][]'s conditions; no other angle is."""
    load = ConstantLoad(_mean_P(scene))
    if rest_rate(scene.mech, load, 0.0) <= 0 < rest_rate(scene.mech, load, np.pi):
        return float(np.pi)
    return 0.0


@eqx.filter_jit
def _chart(scene, amps, freqs, structure, rest):
    return jax.vmap(lambda a, f: floquet_max(scene, a, f, structure=structure,
                                             rest=rest))(amps, freqs)


def mathieu_tongue(scene, amplitude) -> tuple[float, float]:
    """The first tongue's edges `(f_lo, f_hi)`, Hz, at slider-force amplitude `amplitude`
    (N), from first-order harmonic balance of the damped Mathieu equation:
    `(w0^2 - nu^2)^2 + (2 zeta w0 nu)^2 = (w0^2 h / 2)^2`, `nu = pi f`, `h = xi_P P1 /
    xi0`. Accurate to O(h^2); `(nan, nan)` below the damping's threshold (h ~ 4 zeta)."""
    P0 = float(_mean_P(scene))
    lin = linearize(scene.mech, ConstantLoad(P0))
    xi_P = float(linearize(scene.mech, ConstantLoad(P0 + 1.0)).xi) - float(lin.xi)
    w0, zeta = float(lin.omega_n), float(lin.zeta)
    h = abs(xi_P * float(amplitude) / float(lin.xi))
    a = 1 - 2 * zeta * zeta
    disc = a * a - 1 + h * h / 4
    if disc < 0:
        return float("nan"), float("nan")
    x = w0 * w0 * np.array([a - np.sqrt(disc), a + np.sqrt(disc)])
    nu = np.sqrt(np.maximum(x, 0.0))
    return float(nu[0] / np.pi), float(nu[1] / np.pi)
