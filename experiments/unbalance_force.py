"""A term of one's own, fitted: a crank unbalance torque `a sin(phi) + b cos(phi)`.

The crank of a motor-driven rig carries an unknown unbalance: a mass off its axis, whose
weight gives the torque `tau_u = a sin(phi) + b cos(phi)` (N*m; `a` and `b` are the
weight times its offset along and across the crank). The model has no such term, so it
comes in as a user force (`simulate(force=...)`, `fit(force=...)`): an `eqx.Module`
whose float fields are freed as `force.a` and `force.b`.

Run: `python experiments/unbalance_force.py` (about a minute on a laptop's CPU). It
prints the estimates with their 95% intervals against the truth.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402

import crank_jax as cj  # noqa: E402


class Unbalance(eqx.Module):
    """`tau_u(phi) = a sin(phi) + b cos(phi)`, N*m."""

    a: jax.Array
    b: jax.Array

    def __call__(self, t, phi, dphi):
        return self.a * jnp.sin(phi) + self.b * jnp.cos(phi)


def rig(**mech) -> cj.Scene:
    """A crank turned by a constant motor torque, no spring, slider position measured."""
    m = dict(r=0.05, L=0.2, b=0.1, s=0.01, m_c=0.5, m_p=0.3, m_s=0.4, I_c=1e-3, I_p=2e-3,
             k=0.0, c=2e-3, g=9.81)
    m.update(mech)
    return cj.Scene(cj.SliderCrank(**m), torque=cj.ConstantLoad(0.05), phi0=0.0, dphi0=10.0,
                    t1=2.0, sensors=(cj.Sensor("x_s"),))


def run(seed: int = 0, progress: bool = False):
    """Synthesise 2 s at 100 Hz with 20 um of slider noise under a known unbalance, then
    fit `a`, `b`, `c` and the state from a start without any unbalance."""
    truth = Unbalance(jnp.asarray(0.02), jnp.asarray(-0.01))
    data = cj.synthesize(rig(), rate=100.0, noise_std={"x_s": 2e-5}, seed=seed, force=truth)
    start = Unbalance(jnp.asarray(0.0), jnp.asarray(0.0))
    res = cj.fit(rig(c=2.5e-3), data, free=("force.a", "force.b", "c", "phi0", "dphi0"),
                 force=start, progress=progress, warn=False)
    return truth, res


def main() -> None:
    truth, res = run(progress=True)
    print(res.summary())
    for name, want in (("force.a", float(truth.a)), ("force.b", float(truth.b)),
                       ("c", 2e-3)):
        lo, hi = res.ci95[name] or (float("nan"), float("nan"))
        print(f"{name}: {res.values[name]:.5g} (truth {want:g}), 95% CI [{lo:.5g}, {hi:.5g}]")


if __name__ == "__main__":
    main()
