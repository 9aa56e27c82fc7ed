"""Host data onto the device without a compiled program.

In jax 0.10, `jnp.asarray` of a numpy array (or a list of numbers) runs a small compiled
program (`stage`), one per shape and dtype, compiled in a fresh process or looked up in
the persistent compilation cache in a warm one. A fit builds its problems from host data
of about fifteen shapes (segments, weights, scales, start coordinates), so those were a
noticeable part of a cold fit (docs/benchmarks/design-figures.md). `jax.device_put`
copies the same numbers with no program.
"""

from __future__ import annotations

import jax
import numpy as np

__all__ = ["device_array"]


def device_array(x, dtype=None) -> jax.Array:
    """`x` (a numpy array, a numpy scalar, a list of numbers, or a Python number with
    `dtype` given) as a JAX array with the dtype `jnp.asarray(x, dtype)` gives it, copied
    without a compiled program. Always strongly typed: not for a Python number without
    `dtype`, which `jnp.asarray` makes weakly typed. A JAX array passes through as it is
    (cast when `dtype` asks)."""
    if isinstance(x, jax.Array):
        return x if dtype is None else x.astype(dtype)
    return jax.device_put(np.asarray(x, dtype))
