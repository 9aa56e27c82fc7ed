"""The Gauss-Newton step at a point of a fit, with each coordinate's standard error at
the noise level, and the step in words: what LM's termination tests
([`optimize`][crank_jax.identify.optimize]) judge in the data's units.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

__all__ = ["Step", "gauss_newton", "direction"]


class Step(NamedTuple):
    """The Gauss-Newton step at a point, in the problem's coordinates `z`."""

    dz: np.ndarray  # (p,) the step
    se: np.ndarray  # (p,) standard errors at the noise level (inf: flat)
    decrease: float  # the cost decrease the linearisation predicts, 0.5 |J dw|^2

    @property
    def largest(self) -> float:
        """The step's largest move of a coordinate over its standard error."""
        return float(np.max(np.abs(self.dz) / self.se, initial=0.0))


def gauss_newton(model, w: np.ndarray, r: np.ndarray, J: np.ndarray,
                  noise: float) -> Step:
    """The Gauss-Newton step at `w` from its SVD, with each coordinate's standard error at
    the noise level `noise` (singular values below `eps max(N, q)` of the largest count
    as 0, as `lstsq`'s default)."""
    U, S, Vt = np.linalg.svd(J, full_matrices=False)
    keep = S > S[0] * np.finfo(float).eps * max(J.shape) if S.size and S[0] > 0 else S > 0
    Ur, Sr, Vr = U[:, keep], S[keep], Vt[keep].T
    ur = Ur.T @ r
    dw = -Vr @ (ur / Sr)
    # The view's map onto the problem's coordinates, linearised at `w` (a subspace's
    # basis, a pinned coordinate's insertion, value coordinates' chain rule): `dz/dw`.
    L = model.restrict(np.eye(np.asarray(model.lift(w)).shape[0]), w)
    dz = L @ dw
    A = L @ (Vr / Sr)
    se = noise * np.sqrt(np.sum(A * A, axis=1))
    return Step(dz, np.where(se > 0, se, np.inf), 0.5 * float(ur @ ur))


def direction(names, dz: np.ndarray, se: np.ndarray) -> str:
    """The step `dz` as a combination of the named coordinates, each in units of its
    standard error (unit length; terms below 0.2 left out), e.g. "0.86 tau0 - 0.51 P0";
    coordinates beyond `names` (segment states) are summed up as one term."""
    v = np.where(np.isfinite(se), dz / se, 0.0)
    norm = float(np.linalg.norm(v))
    if norm == 0 or not math.isfinite(norm):
        return "no direction"
    v = v / norm
    terms = [(float(x), n) for x, n in zip(v, names)]
    rest = float(np.linalg.norm(v[len(names):]))
    terms = sorted([t for t in terms if abs(t[0]) >= 0.2], key=lambda t: -abs(t[0]))
    out = " ".join(f"{'-' if x < 0 else '+'} {abs(x):.2f} {n}" for x, n in terms)
    if rest >= 0.2:
        out += f" + {rest:.2f} (segment states)"
    return out.lstrip("+ ").replace("- ", "-", 1) if out.startswith("-") else out.lstrip("+ ")
