"""Test configuration: float64 everywhere, a small CPU-only JAX, shared helpers."""

import os

os.environ.setdefault("CRANK_JAX_NO_CACHE", "1")  # tests must not depend on a warm cache

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
import pytest  # noqa: E402

import crank_jax as cj  # noqa: E402


def tree_allclose(a, b, rtol=1e-10, atol=1e-12) -> bool:
    """True when two pytrees have the same structure and close leaves."""
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    return ta == tb and all(
        np.allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=atol) for x, y in zip(la, lb)
    )


def flip_byte(i: int):
    """A damage for a stored file: its bytes with bit 0 of byte `i` (mod the length)
    flipped."""
    def damage(b: bytes) -> bytes:
        b = bytearray(b)
        b[i % len(b)] ^= 0x01
        return bytes(b)
    return damage


def random_mech(rng: np.random.Generator, **overrides) -> "cj.SliderCrank":
    """A random valid mechanism with every body present (geometry spans r/L in 0.05..0.9)."""
    r = rng.uniform(0.02, 0.1)
    L = r / rng.uniform(0.05, 0.9)
    v = dict(
        r=r, L=L, b=rng.uniform(0, L), s=rng.uniform(0, r), m_c=rng.uniform(0.1, 2),
        m_p=rng.uniform(0.1, 2), m_s=rng.uniform(0.1, 2), I_c=rng.uniform(1e-5, 1e-3),
        I_p=rng.uniform(1e-5, 1e-2), k=rng.uniform(1, 10), c=rng.uniform(0, 0.05),
        g=rng.uniform(5, 10),
    )
    v.update(overrides)
    return cj.SliderCrank(**v)


@pytest.fixture
def rng():
    return np.random.default_rng(20261121)


@pytest.fixture(scope="session")
def lab_rig():
    return cj.load_scene("lab-rig")
