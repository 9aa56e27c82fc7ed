"""Every member of a `jax.vmap`-ed batch gets its own answer: a member that needs tiny
steps, or that runs out of its step budget, changes neither the others' results nor their
statuses (issue 26, item 3)."""

import jax
import jax.numpy as jnp
import numpy as np

import crank_jax as cj

RTOL = 1e-8


def _solve(mech, k, ts, max_steps):
    return cj.simulate(mech.replace(k=k), 1.0, 0.0, ts, rtol=RTOL, atol=RTOL * 1e-2,
                       max_steps=max_steps, throw=False)


def test_stiff_and_failing_members_leave_the_others_alone(lab_rig):
    ts = jnp.linspace(0, 3, 301)
    mech, budget = lab_rig.mech, 3000
    # Healthy (k 2 and 3 N m/rad), one that needs ~6x more steps but finishes (k 50),
    # and one that cannot finish within the budget (k 1e7: steps of ~1e-5 s).
    ks = jnp.array([2.0, 1e7, 50.0, 3.0])
    batch = jax.jit(jax.vmap(lambda k: _solve(mech, k, ts, budget)))(ks)
    ok = np.asarray(batch.ok)
    assert ok.tolist() == [True, False, True, True]
    assert int(batch.num_steps[1]) == budget  # the failing member's own count
    failing = _solve(mech, ks[1], ts, budget)  # and its own outputs, as alone
    np.testing.assert_allclose(batch.phi[1], failing.phi, rtol=0, atol=10 * RTOL)
    for i in (0, 2, 3):
        alone = _solve(mech, ks[i], ts, budget)
        assert bool(alone.ok)
        np.testing.assert_allclose(batch.phi[i], alone.phi, rtol=0, atol=10 * RTOL)
        np.testing.assert_allclose(batch.dphi[i], alone.dphi, rtol=0,
                                   atol=10 * RTOL * float(jnp.max(jnp.abs(alone.dphi))))
        # Its own steps, not the stiff member's: a few more than alone where its steps are
        # cut at the end of the save window that the slowest member holds back.
        assert 0.99 * alone.num_steps <= batch.num_steps[i] <= 1.25 * alone.num_steps


def test_a_sweep_keeps_its_healthy_samples(lab_rig):
    # A sweep with solver="dopri8-adaptive" batches a chunk through the same lockstep
    # rule: one sample out of budget there made every sample of its chunk "max_steps"
    # with zero outputs (before issue 26). Now it is the only one.
    kw = dict(t1=2.0, num_saves=201, solver="dopri8-adaptive", chunk_size=4,
              max_steps=2000, sort=False)
    outs = ("final_phi", "peak_phi")
    mixed = cj.run_sweep(lab_rig, {"k": np.array([2.0, 1e7, 3.0])}, outs, **kw)
    healthy = cj.run_sweep(lab_rig, {"k": np.array([2.0, 3.0])}, outs, **kw)
    ok, failed = cj.sweep.STATUS.index("ok"), cj.sweep.STATUS.index("max_steps")
    assert mixed.status.tolist() == [ok, failed, ok]
    for name in outs:
        np.testing.assert_allclose(mixed.outputs[name][[0, 2]], healthy.outputs[name],
                                   rtol=0, atol=1e-7)
