"""Nonlinear vibrations of the lab rig: how the natural frequency falls with amplitude (the
backbone), where a harmonically driven crank's response jumps (a forced response curve with
Floquet stability), and a stiffness tuned by gradient so that the resonance moves away from
an operating frequency."""

import jax

jax.config.update("jax_enable_x64", True)  # float64 for accuracy claims

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402

import crank_jax as cj  # noqa: E402

rig = cj.load_scene("lab-rig")

# 1. The backbone: free, undamped swings of growing amplitude.
bb = cj.backbone(rig.mech, [0.01, 0.5, 1.0, 1.5])
print(f"linear natural frequency {float(bb.linear_frequency_hz):.4f} Hz")
for a, f in zip(bb.amplitude, bb.frequency_hz):
    print(f"  amplitude {float(a):4.2f} rad: {float(f):.4f} Hz")

# 2. Drive the crank with a harmonic torque of 0.05 N*m and follow the periodic orbits
#    through the resonance: the softening peak leans left and folds.
driven = eqx.tree_at(lambda s: s.torque, rig, cj.HarmonicLoad(0.0, 0.05, 4.0))
resp = cj.forced_response(driven, (3.0, 5.5), backbone_points=20)
(branch,) = resp.branches
print(f"{len(branch.freq_hz)} orbits, {int((~branch.stable).sum())} unstable")
for fold in resp.folds:
    print(f"  fold at {fold['freq_hz']:.4f} Hz, amplitude {fold['amplitude']:.3f} rad")
from crank_jax.vibration.plots import plot_response  # noqa: E402

plot_response(resp, "response.png")
print("wrote response.png")

# 3. The rig must run at 4.0 Hz, inside the hysteresis region: a disturbance can throw it
#    onto the large orbit. Stiffen the shaft until the small orbit's amplitude at 4.0 Hz
#    is 0.1 rad, by Newton steps on k with d(amplitude)/dk from the implicit function
#    theorem (no finite differences, no unrolled continuation).
f_op, target = 4.0, 0.1


def amplitude(k):
    return cj.periodic_orbit(eqx.tree_at(lambda s: s.mech.k, driven, k), f_op).amplitude


value_and_grad = jax.jit(jax.value_and_grad(amplitude))
k = jnp.asarray(2.0)
for it in range(6):
    a, da = value_and_grad(k)
    print(f"  k = {float(k):.5f} N*m/rad: amplitude {float(a):.5f} rad, "
          f"d amplitude/dk = {float(da):+.4f}")
    if abs(float(a) - target) < 1e-6:
        break
    k = k - (a - target) / da

tuned = eqx.tree_at(lambda s: s.mech.k, driven, k)
resp2 = cj.forced_response(tuned, (3.0, 6.5))
print("folds after tuning:", [f"{f['freq_hz']:.3f} Hz" for f in resp2.folds],
      f"(operating frequency {f_op} Hz)")
