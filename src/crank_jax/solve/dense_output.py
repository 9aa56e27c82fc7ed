"""Dopri8's dense output, as the fused adaptive solver evaluates it (adaptive.py) and the
discrete adjoint differentiates it (adjoint.py, stage_adjoint.py): diffrax's polynomial
coefficients, formed per step and evaluated once per block of step attempts for the
save times the block covers."""

from __future__ import annotations

import functools

import jax.numpy as jnp
import numpy as np

from . import library_api as compat

__all__ = ["dopri8_dense", "dense_coefficients", "window_values"]


@functools.cache
def dopri8_dense() -> np.ndarray:
    """diffrax's Dopri8 dense output: `y(t0 + theta h) = y0 + theta sum_i P_i(theta) h k_i`,
    `P_i` the polynomial in row i (highest power first) over the 14 stages (the 14th is
    `f(t1, y1)`, first same as last). Shape (14, powers)."""
    return compat.dopri8_dense_coefficients()


def dense_coefficients(coeffs, h, ks):
    """The dense output's polynomial coefficients times h, highest power first: a list of
    (..., N) arrays, one per power (unrolled over the nonzero stage weights)."""
    d = []
    for j in range(coeffs.shape[1]):
        acc = None
        for i, k in enumerate(ks):
            a = float(coeffs[i, j])
            if a != 0.0:
                acc = a * k if acc is None else acc + a * k
        d.append(h * acc)
    return d


def window_values(dense, taken, twr):
    """The dense output at the window's save times `twr`, (W, 1, ..., 1) as rows against
    the members' times (or (W, B, 1), each member's own): each one that lies in `(t, t1]`
    of an accepted attempt in `taken` (per member of a batch) takes that attempt's
    coefficients (a select per attempt), then one polynomial evaluation for the whole
    window.

    **Returns:** `(values, covered)`: values of shape (W,) + the packed state's shape,
    and where an attempt covered the save time, shape (W,) + (..., 1) (save times no
    attempt covers are pending: their values are zeros, written by a later block)."""
    theta = covered = base = coef = None
    for rec in taken:
        mine = rec.ok[None] & (twr > rec.t[None]) & (twr <= rec.t1[None])
        d = dense_coefficients(dense, rec.h, rec.ks)
        th = (twr - rec.t[None]) / rec.h[None]
        theta = jnp.where(mine, th, 0.0 if theta is None else theta)
        covered = mine if covered is None else covered | mine
        base = jnp.where(mine, rec.y[None], 0.0 if base is None else base)
        coef = [jnp.where(mine, dj[None], 0.0 if coef is None else cj)
                for dj, cj in zip(d, coef or [None] * len(d))]
    poly = coef[0]
    for cj in coef[1:]:
        poly = poly * theta + cj
    return base + theta * poly, covered
