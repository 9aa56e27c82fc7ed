"""The fit's compiled programs, and the residual views the optimisers see.

Each is a [`PersistentProgram`][]: kept between processes where it holds no host callback
(the residuals' solves are `simulate`'s core without runtime checks; see
`Problem.simulate_segments`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ..runtime.persistent import FAST_COMPILE, PersistentProgram, fast_compile_on_cpu
from ..runtime.xla_flags import small_loop_bytes
from .problem import Problem

__all__ = ["Program", "residuals_at", "jacobian_at", "Subspace",
           "InValues", "Pinned", "segment_coloring", "compile_options", "FAST_COMPILE"]


def compile_options(problem, *_) -> dict:
    """The XLA compile options of a fit program's call on `problem` (a [`Problem`][], or a
    view of one with a `.problem`): [`FAST_COMPILE`][] on the CPU where it gives the same
    bits as XLA's defaults: a multiple-shooting problem, and any problem under crank-jax's
    CPU flags (`xla_flags.py`). Not a single-shooting problem under XLA's defaults: there
    the two emitters round its scalar solve differently, and a fit's result must not
    depend on a compile choice."""
    inner = getattr(problem, "problem", problem)
    if getattr(inner, "n_extra", 0) > 0 or small_loop_bytes() is not None:
        return fast_compile_on_cpu()
    return {}


def Program(fn, name: str) -> PersistentProgram:
    """A compiled function of the fit, kept between processes (see
    [`PersistentProgram`][]), compiled with [`compile_options`][]."""
    return PersistentProgram(fn, name, compile_options)


def _residuals(problem, z):
    return problem.residuals(z)


def segment_coloring(problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    """A column colouring of a multiple-shooting problem's Jacobian `dr/dz` (N, P), for
    computing it from few forward-mode directions (Curtis, Powell and Reid, 1974).

    A segment's initial state moves only that segment's samples and the continuity
    defects at its ends, so the states of segments two apart, and of different records,
    touch disjoint rows: one direction per global coordinate and four for all the segment
    states (state component x segment parity) give every column.

    **Returns:** `(color (P,) int, mask (N, P) bool)`: column `j` of the Jacobian is
    column `color[j]` of the compressed one, on the rows where `mask[:, j]` (its possible
    nonzeros). Host-side, from the problem's static shapes."""
    p = problem.p
    n_z = p + problem.n_extra
    # (S, m, channels) per record; each channel's rows are a block of S * m
    sizes = [tuple(e.seg.ts.shape) + (len(e.channels),) for e in problem.exps]
    n_data = sum(S * m * C for S, m, C in sizes)
    n_rows = n_data + sum(2 * (S - 1) for S, _, _ in sizes)
    color = np.arange(n_z)
    mask = np.zeros((n_rows, n_z), dtype=bool)
    mask[:, :p] = True
    row, cont, col = 0, n_data, p
    for S, m, C in sizes:
        for s in range(1, S):  # segment s's state; segment 0's is a global (or fixed)
            for c in range(2):
                j = col + 2 * (s - 1) + c
                color[j] = p + 2 * (s % 2) + c
                for ch in range(C):  # its samples, in every channel
                    base = row + ch * S * m
                    mask[base + s * m: base + (s + 1) * m, j] = True
                for d in (s - 1, s):  # the defects at its start and its end
                    if d < S - 1:
                        mask[[cont + d, cont + S - 1 + d], j] = True
        row, cont, col = row + S * m * C, cont + 2 * (S - 1), col + 2 * (S - 1)
    return color, mask


def _jacobian(problem, z):
    def f(x):
        r, failed, steps = problem.residuals(x)
        return r, (r, failed, steps)

    if problem.n_extra == 0:
        J, (r, failed, steps) = jax.jacfwd(f, has_aux=True)(z)
        return r, failed, steps, J
    # Multiple shooting: the compressed Jacobian from few directions (`segment_coloring`),
    # the same values: a segment's solve sees the same tangent either way.
    color, mask = segment_coloring(problem)
    seeds = jnp.asarray(np.eye(color.max() + 1)[color].T, dtype=z.dtype)  # (q, P)

    def push(v):
        _, dr, aux = jax.jvp(f, (z,), (v,), has_aux=True)
        return dr, aux

    Jc, aux = jax.vmap(push, out_axes=(-1, None))(seeds)
    r, failed, steps = aux
    return r, failed, steps, jnp.where(mask, Jc[:, color], 0.0)


#: `residuals_at(problem, z) -> (r, n_failed, steps)`, compiled.
residuals_at = Program(_residuals, "residuals")
#: `jacobian_at(problem, z) -> (r, n_failed, steps, J)`: the residuals with their
#: sensitivities `J = dr/dz` (N, p), by forward mode through the ODE solves (one program
#: for both: the fit needs both at its start and at its estimate).
jacobian_at = Program(_jacobian, "jacobian")


class Subspace(eqx.Module):
    """The residuals on the affine subspace `z = z0 + B w` (B: orthonormal columns), used
    to hold exactly flat directions (a common scale) fixed during the optimisation."""

    problem: Problem
    z0: Array
    B: Array

    def residuals(self, w):
        return self.problem.residuals(self.z0 + self.B @ w)

    def lift(self, w: np.ndarray) -> np.ndarray:
        """On the host: the problem's coordinates `z` (p,) of the point `w` (q,)."""
        return np.asarray(self.z0) + np.asarray(self.B) @ w

    def restrict(self, J: np.ndarray, w: np.ndarray) -> np.ndarray:
        """On the host: the sensitivities `dr/dw` (N, q) from `dr/dz` (N, p) (at any `w`:
        the map is affine)."""
        return J @ np.asarray(self.B)


class InValues:
    """The residuals on the affine subspace `u = u0 + B w` of *value* coordinates, for
    LM on the host: every parameter linear in its value (`u_i = value_i / s_i`, `s_i`
    the value at the start), where `problem` has some in log space (`z_i = ln value_i`).

    Why: the equation of motion is linear in the mechanism's coefficients, so the valley
    of a balance such as `tau0 = c dphi + F_s ...` is straight in values and curved in
    logs, and LM crawls along a curved one. Multiple shooting's problems are built in
    linear coordinates for this; this view gives single shooting the same with no second
    compiled program: the diagonal map `u -> z` is applied on the host to the point and,
    by the chain rule, to the sensitivities.

    A point with a log-space value at or below 0 is outside (`lift` gives NaN there),
    which the optimiser sees as a failed point and rejects."""

    def __init__(self, problem: Problem, z0: np.ndarray, B: np.ndarray):
        self.problem = problem
        z0 = np.asarray(z0, dtype=float)
        self.log = np.asarray(problem.log, dtype=bool)
        # u0 = 1 for a log coordinate (its value the scale s), z0 for the others
        self.s = np.where(self.log, np.exp(np.where(self.log, z0, 0.0)), 1.0)
        self.u0 = np.where(self.log, 1.0, z0)
        # `du/dz` at z0 is 1 in every coordinate (u = exp(z) / s = 1 there for a log one),
        # so `B` (orthonormal, as `Subspace`'s) spans the same directions in u as in z.
        self.B = np.asarray(B, dtype=float)

    def _u(self, w) -> np.ndarray:
        return self.u0 + self.B @ np.asarray(w, dtype=float)

    def lift(self, w: np.ndarray) -> np.ndarray:
        """On the host: the problem's coordinates `z` (p,) of the point `w` (q,); NaN in
        a log coordinate whose value is not positive."""
        u = self._u(w)
        ok = ~self.log | (u > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            lg = np.log(np.where(ok, u, 1.0) * self.s)
        return np.where(self.log, np.where(ok, lg, np.nan), u)

    def restrict(self, J: np.ndarray, w: np.ndarray) -> np.ndarray:
        """On the host: `dr/dw` (N, q) at `w` from `dr/dz` (N, p) there."""
        u = self._u(w)
        dz_du = np.where(self.log, 1.0 / np.where(self.log, u, 1.0), 1.0)
        return J @ (dz_du[:, None] * self.B)


class Pinned(eqx.Module):
    """The residuals with coordinate `j` held at `zj` (for profile likelihoods)."""

    problem: Problem
    zj: Array
    j: int = eqx.field(static=True)

    def full(self, zr):
        return jnp.concatenate([zr[:self.j], self.zj[None], zr[self.j:]])

    def residuals(self, zr):
        return self.problem.residuals(self.full(zr))

    def lift(self, zr: np.ndarray) -> np.ndarray:
        """On the host: the problem's coordinates (p,) of the free ones `zr` (p - 1,)."""
        return np.insert(np.asarray(zr, float), self.j, float(self.zj))

    def restrict(self, J: np.ndarray, w: np.ndarray) -> np.ndarray:
        """On the host: the sensitivities to the free coordinates (N, p - 1) (at any `w`)."""
        return np.delete(J, self.j, axis=1)
