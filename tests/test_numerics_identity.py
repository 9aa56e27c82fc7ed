"""Making the numerics explicit (issue 39: the trig form a static field, the step-size
controller and the tableau fields of `AdaptiveDopri8`) changed no number: a single solve,
a lockstep batch and a reverse-mode gradient through the vectorised backward blocks give,
bit for bit, what main (7fdda40, the context-variable trig and the module constants) gave.

The batch's first member differs from the single solve in its last bits (the batch traces
sin, cos and 1/sqrt as arithmetic, the single solve JAX's own), so these values also pin
which form each path traces. They were taken on the 2-core x86-64 development machine
(XLA:CPU, jax 0.10.2); another CPU or XLA may round otherwise."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import crank_jax as cj
from crank_jax.solve.adjoints import DiscreteAdjoint

TS = jnp.linspace(0.0, 0.3, 4)
SINGLE = ["0x1.0000000000000p+0", "-0x1.5d621516a6a4ep-1", "0x1.14138f51e3da0p-7",
          "0x1.142ef8d9f074fp-1"]
BATCH = [["0x1.0000000000000p+0", "-0x1.5d621516a6ed6p-1", "0x1.14138f51b8539p-7",
          "0x1.142ef8d9f07f9p-1"],
         ["0x1.0000000000000p+0", "-0x1.ac967b0c5a966p-1", "0x1.12ff153faf4b1p-1",
          "-0x1.5d9a70b7b3dd5p-3"]]
GRAD = ["-0x1.2d492d17d2402p+0", "-0x1.36378be3b8e89p-5"]


def _phi(mech, theta, adjoint="reverse"):
    # A harmonic slider force (its amplitude a parameter) and a two-tone torque: the
    # loads' sines follow the field's form too.
    k, P1 = theta
    torque = cj.MultiSineLoad(jnp.array([0.01, 0.02]), jnp.array([2.0, 5.0]),
                              jnp.array([0.0, 1.0]))
    return cj.simulate(mech.replace(k=k), 1.0, 0.0, TS, load=cj.HarmonicLoad(0.5, P1, 3.0, 0.2),
                       torque=torque, solver="dopri8-adaptive", adjoint=adjoint).phi


def _hex(x):
    return np.array([float.fromhex(v) for v in np.ravel(x)]).reshape(np.shape(x))


# ~35 s and ~50 s of compiling on 2 loaded cores: the fast tier checks the forms by the
# traced primitives instead (tests/test_trig.py).
@pytest.mark.slow
def test_a_single_solve_and_a_lockstep_batch_are_mains_bit_for_bit(lab_rig):
    single = _phi(lab_rig.mech, jnp.array([2.0, 2.0]))
    np.testing.assert_array_equal(single, _hex(SINGLE))
    batch = jax.vmap(lambda th: _phi(lab_rig.mech, th))(jnp.array([[2.0, 2.0], [2.3, 1.0]]))
    np.testing.assert_array_equal(batch, _hex(BATCH))


@pytest.mark.slow
def test_the_gradient_by_the_vectorised_blocks_is_mains_bit_for_bit(lab_rig):
    # The backward pass's blocks (XLA's defaults) evaluate the field in the arithmetic form.
    jax.clear_caches()  # no backward program traced by an earlier test under another setting
    blocks = DiscreteAdjoint(backward="blocks")
    grad = jax.grad(lambda th: jnp.sum(_phi(lab_rig.mech, th, blocks) ** 2))(
        jnp.array([2.0, 2.0]))
    np.testing.assert_array_equal(grad, _hex(GRAD))
