"""A free-decay fit: a lab rig released from 1 rad, its record in a CSV file, then the
shaft's stiffness k and damping c fitted with the initial state, and an HTML report."""

import jax

jax.config.update("jax_enable_x64", True)  # float64 for accuracy claims

import crank_jax as cj  # noqa: E402

truth = cj.load_scene("lab-rig")  # released from 1 rad, no load
record = cj.synthesize(truth, t1=3.0, rate=200.0, noise_std=1e-3, seed=0)
cj.save_data(record, "decay.csv")  # as a rig's logger would write it: t,phi

data = cj.load_data("decay.csv")
# The model to fit: the rig's known geometry and masses, a guess 20% off in k, 2x in c.
start = cj.Scene(truth.mech.replace(k=2.4, c=0.02), phi0=1.0)
res = cj.fit(start, data, free=("k", "c", "phi0", "dphi0"), progress=False)
print(res.summary())
print(f"truth: k = {float(truth.mech.k):g} N*m/rad, c = {float(truth.mech.c):g} N*m*s/rad")
res.report("decay-report.html", scene=start, title="free decay of the lab rig")
print("wrote decay-report.html")
