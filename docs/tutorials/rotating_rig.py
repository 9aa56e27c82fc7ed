"""A motor-driven, rotating offset slider-crank with a slide sensor: two records at
different motor voltages, fitted under defaults from generic start values, and the model
validated on a third voltage. (The full study, with a coverage run over seeds per channel
configuration, is `experiments/rotating_rig.py`.)"""

import jax

jax.config.update("jax_enable_x64", True)

import crank_jax as cj  # noqa: E402
from crank_jax.identify import fitted_scene  # noqa: E402
from crank_jax.model import InputLoad  # noqa: E402

# The rig: 8 mm offset, a mount tilted by 0.35 rad, no spring, Coulomb friction in the
# crank bearing, a DC motor whose torque is gain * volts (its back-EMF is the damping c).
mech = cj.SliderCrank(r=0.05, L=0.2, b=0.1, s=0.01, m_c=0.1, m_p=0.05, m_s=0.1, I_c=2e-3,
                      I_p=2e-4, k=0.0, c=0.01, g=9.81, e=0.008, T_c=0.02, w_c=0.05,
                      gravity_angle=0.35)
# What the logger sees: an encoder counting the other way from an unknown zero (deg), and
# a slide sensor in mm counting towards the crank; data = scale * model + offset.
sensors = (cj.Sensor("phi", "wheel_deg", "deg", scale=-1.0, offset=-3.083),
           cj.Sensor("x_s", "slide_mm", "mm", scale=-1.0, offset=0.2948))


def run(volts: float, seed: int) -> cj.Data:
    """A record at constant `volts`: 50 Hz with 3 ms loop jitter (actual times logged), a
    4096-count encoder, started 0.5 s after the motor."""
    motor = InputLoad(gain=0.03, column="volts").bind([0.0, 4.0], [volts, volts])
    scene = cj.Scene(mech, torque=motor, phi0=0.0, dphi0=5.0, t1=3.0, sensors=sensors)
    return cj.synthesize(scene, t_start=0.5, rate=50.0, jitter_std=3e-3, quantization=4096,
                         noise_std={"phi": 2e-3, "x_s": 5e-5}, seed=seed,
                         timestamps="actual")


# Generic start values: the gain and damping off by 2x, no friction. One voltage alone
# cannot tell Coulomb friction from a constant torque; two records (the gain shared) can.
start = cj.Scene(mech.replace(c=0.02, T_c=0.0), torque=InputLoad(gain=0.015, column="volts"),
                 phi0=0.0, dphi0=5.0, t1=3.0, sensors=sensors)
res = cj.fit(start, [run(6.0, 1), run(9.0, 2)], free=("tau_gain", "c", "T_c", "phi0", "dphi0"),
             progress=False)
print(res.summary())  # per channel: rms and noise level in each channel's SI unit

val = cj.validate(fitted_scene(start, res), run(7.5, 3), init_window=0.5)
print(val.summary())
