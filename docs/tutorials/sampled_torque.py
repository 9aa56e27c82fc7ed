"""A fit with a sampled torque: the crank is shaken by a measured torque (a `tau` column in
the record), which fixes the common scale of the inertial parameters, so the crank's
inertia I_c can be fitted beside k and c."""

import jax

jax.config.update("jax_enable_x64", True)

import crank_jax as cj  # noqa: E402

rig = cj.load_scene("lab-rig")
# The rig's shaker: a sum of three sines, N*m (in a real test, whatever was measured).
shaker = cj.MultiSineLoad([0.08, 0.05, 0.04], [2.0, 3.5, 6.0], [0.0, 1.0, 2.0])
truth = cj.Scene(rig.mech, torque=shaker, phi0=0.3)
cj.save_data(cj.synthesize(truth, t1=4.0, rate=200.0, noise_std=1e-3, seed=2), "shaken.csv")

data = cj.load_data("shaken.csv")  # t, phi, tau: the tau column becomes a sampled load
print("columns:", ", ".join(data.columns()), f"({data.n} samples)")
start = cj.Scene(rig.mech.replace(k=2.4, c=0.004, I_c=3e-4), phi0=0.3)
res = cj.fit(start, data, free=("k", "c", "I_c", "phi0", "dphi0"), progress=False)
print(res.summary())
print("truth: " + ", ".join(f"{n} = {float(getattr(rig.mech, n)):g}" for n in ("k", "c", "I_c")))
