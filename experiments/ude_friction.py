"""A universal differential equation: learn an unknown friction law through the solver.

The "truth" is the lab rig with a crank bearing whose friction is Coulomb plus Stribeck
(a torque that is not in crank-jax's model): `tau_f = -(T_c + T_s exp(-(w/w_s)^2))
tanh(w / w_c) - c w`. The record is its angle at 100 Hz with 0.5 mrad of noise. The model
is the same mechanism with a learned torque `-c phi' + MLP(phi')` added to the generalised
force through `simulate(..., force=...)`; `c` and the MLP's weights are trained with optax
(Adam)
on the squared angle error, with gradients by reverse mode through the ODE solve. The
figure shows the learned friction curve against the true one over the range of rates the
record visits.

Run: `python experiments/ude_friction.py [--steps 300] [--out docs/figures/ude_friction.png]`
(about 2-4 min on a 2-core CPU). `--smoke` runs 5 steps for CI.
"""

from __future__ import annotations

import argparse
import json
import time

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402

import crank_jax as cj  # noqa: E402
from crank_jax.report.plotting import pyplot, save_figure  # noqa: E402
from crank_jax.runtime.io import atomic_write  # noqa: E402

T_C, T_S, W_S, W_C, C_TRUE = 0.004, 0.006, 0.8, 0.2, 0.001


def true_friction(t, phi, dphi):
    """The rig's bearing torque, N*m: Coulomb + Stribeck + viscous (unknown to the model)."""
    del t, phi
    stribeck = T_C + T_S * jnp.exp(-((dphi / W_S) ** 2))
    return -stribeck * jnp.tanh(dphi / W_C) - C_TRUE * dphi


class FrictionMLP(eqx.Module):
    """A learned bearing torque `f(phi') -> N*m`: a viscous term `-c phi'` (its `c`
    learned too) plus an MLP for the rest, odd in phi' by construction (friction opposes
    motion). The MLP sees the rate in units of a typical slip rate, where the Coulomb and
    Stribeck shapes live."""

    mlp: eqx.nn.MLP
    c: jax.Array
    """The viscous coefficient in units of `c_scale` (O(1), as Adam's steps are)."""
    slip_rate: float = eqx.field(static=True)
    torque_scale: float = eqx.field(static=True)
    c_scale: float = eqx.field(static=True)

    def __call__(self, t, phi, dphi):
        del t, phi
        x = jnp.atleast_1d(dphi / self.slip_rate)
        odd = self.mlp(x)[0] - self.mlp(-x)[0]
        return self.torque_scale * odd - self.c_scale * self.c * dphi


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--smoke", action="store_true", help="5 steps, no figure (CI)")
    ap.add_argument("--out", default="docs/figures/ude_friction.png")
    ap.add_argument("--json", default="experiments/results/ude_friction.json")
    args = ap.parse_args(argv)
    steps = 5 if args.smoke else args.steps

    scene = cj.load_scene("lab-rig")
    mech = scene.mech.replace(c=0.0)  # all damping is in the unknown law
    ts = jnp.linspace(0.0, 4.0, 401)
    phi0 = 0.8
    truth = cj.simulate(mech, phi0, 0.0, ts, force=true_friction)
    rng = np.random.default_rng(0)
    data = truth.phi + 5e-4 * rng.standard_normal(ts.shape)
    rate_scale = float(jnp.max(jnp.abs(truth.dphi)))

    key = jax.random.PRNGKey(0)
    model = FrictionMLP(eqx.nn.MLP(1, 1, 16, 2, activation=jnp.tanh, key=key),
                        jnp.asarray(0.0), 1.0, 0.01, 1e-3)

    def loss(model):
        tr = cj.simulate(mech, phi0, 0.0, ts, force=model, rtol=1e-7, atol=1e-9)
        return jnp.mean((tr.phi - data) ** 2)

    opt = optax.adam(3e-3)
    params, static = eqx.partition(model, eqx.is_inexact_array)
    state = opt.init(params)

    @eqx.filter_jit
    def step(params, state):
        value, grad = eqx.filter_value_and_grad(
            lambda p: loss(eqx.combine(p, static)))(params)
        updates, state = opt.update(grad, state, params)
        return eqx.apply_updates(params, updates), state, value

    t0 = time.perf_counter()
    history = []
    for i in range(steps):
        params, state, value = step(params, state)
        history.append(float(value))
        if i % 25 == 0 or i == steps - 1:
            print(f"step {i:4d}  rms angle error {np.sqrt(float(value)):.3e} rad")
    seconds = time.perf_counter() - t0
    model = eqx.combine(params, static)

    w = jnp.linspace(-rate_scale, rate_scale, 201)
    learned = jax.vmap(lambda x: model(0.0, 0.0, x))(w)
    true = jax.vmap(lambda x: true_friction(0.0, 0.0, x))(w)
    curve_rms = float(jnp.sqrt(jnp.mean((learned - true) ** 2)))
    result = {
        "steps": steps, "seconds": seconds, "rms_angle_error_start": float(np.sqrt(history[0])),
        "rms_angle_error_end": float(np.sqrt(history[-1])),
        "friction_curve_rms_error": curve_rms,
        "friction_torque_scale": float(jnp.max(jnp.abs(true))),
    }
    print(json.dumps(result, indent=1))
    if args.smoke:
        return
    with atomic_write(args.json) as f:
        json.dump(result, f, indent=1)
    plt = pyplot()
    fig, (a0, a1) = plt.subplots(1, 2, figsize=(10, 3.8))
    a0.plot(w, 1e3 * true, lw=2, label="true (Coulomb + Stribeck + viscous)")
    a0.plot(w, 1e3 * learned, lw=1.2, ls="--", label="learned MLP")
    a0.set_xlabel("phi' [rad/s]")
    a0.set_ylabel("bearing torque [mN m]")
    a0.legend(fontsize=8)
    a0.grid(alpha=0.3)
    fitted = cj.simulate(mech, phi0, 0.0, ts, force=model)
    a1.plot(ts, data, ".", ms=2, label="record")
    a1.plot(ts, fitted.phi, lw=1, label="UDE model")
    a1.set_xlabel("t [s]")
    a1.set_ylabel("phi [rad]")
    a1.legend(fontsize=8)
    a1.grid(alpha=0.3)
    fig.suptitle(f"Learned friction law after {steps} Adam steps "
                 f"(curve rms error {1e3 * curve_rms:.2g} mN m)", fontsize=10)
    save_figure(fig, args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
