"""Records of other lengths reuse the fit's compiled programs: each row (a single-shooting
record, a multiple-shooting segment) is padded to a coarse ladder of its own length and the
segments to a row count of their class, with weight-0 samples and inactive rows, and the
padding changes no value."""

from __future__ import annotations

import contextlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import crank_jax as cj
from crank_jax.identify import segments, start
from crank_jax.identify.fit_plan import basis
from crank_jax.identify.motion_start import motion_start
from crank_jax.identify.problem import build_problem
from crank_jax.identify.programs import jacobian_at, residuals_at
from crank_jax.identify.segments import make_segments, row_bucket, segment_layout
from crank_jax.identify.start import padded_rows

FREE = ("k", "c", "phi0", "dphi0")
_COMPILE = "/jax/core/compile/backend_compile_duration"
_TRACE = "/jax/core/compile/jaxpr_trace_duration"


@contextlib.contextmanager
def counting():
    """Count JAX's traces and compiles in the block: yields a dict of the counts."""
    counts = {_COMPILE: 0, _TRACE: 0}

    def listen(event, duration, **_):
        if event in counts:
            counts[event] += 1

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        yield counts
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)


def _record(scene, t1, seed):
    return cj.synthesize(scene, t1=t1, rate=100.0, noise_std=1e-3, seed=seed)


def _problem(scene, data, segments, pad=True):
    return build_problem(scene.mech, [(data, scene.load, scene.torque, 1.0, 0.0)], FREE,
                         {"k": 2.0, "c": 0.002}, [segments], solver="tsit5", rtol=1e-8,
                         atol=1e-10, max_steps=4096, pad=pad, linear=segments > 1)


def _z(prob, data):
    """Start coordinates: the globals near the truth, each segment state from the data
    at its first sample (as `channel_noise.segment_states` starts them)."""
    first = np.asarray(prob.exps[0].seg.first)[1:]
    dphi = np.gradient(data.phi, data.ts)
    e = prob.exps[0]
    states = np.stack([data.phi[first] / float(e.ref_phi),
                       dphi[first] / float(e.ref_dphi)], axis=1).reshape(-1)
    return np.concatenate([prob.to_z([2.1, 0.0025, 1.0, 0.0]), states])


@pytest.mark.parametrize("S", [1, 2, 3, 4, 5, 6, 8, 12, 16, 24, 32, 48])
def test_segment_layout_holds_every_record_of_its_bucket(S):
    # The rows hold every segment of every record, and their shape is a function of the
    # segment count's class and of the longest segment's row ladder alone: not of the
    # record's length.
    for n in (1001, 1101, 1152, 1153, 1201, 1401, 1728, 4001):
        rows, m = segment_layout(n, S)
        assert rows >= S and rows & (rows - 1) == 0
        bounds = np.linspace(0, n - 1, S + 1).round().astype(int)
        own = np.max(np.diff(bounds)) + 1 if S > 1 else n
        assert own <= m == row_bucket(own) < 2 * own, (n, S)
        seg = make_segments(np.arange(n) * 0.01, np.zeros(n), S)
        assert seg.ts.shape == (rows, m) and float(np.sum(seg.on)) == S
        # A row's own samples increase; its padding repeats the last (no solver step).
        d = np.diff(np.asarray(seg.ts), axis=1)
        assert np.all(d >= 0)
        assert np.array_equal(np.sum(d > 0, axis=1), np.asarray(seg.end))
        rows_eom, keep = padded_rows([tuple(np.zeros(n - 12) for _ in range(4))])
        assert rows_eom[0][0].shape == (row_bucket(n - 12),) and keep.sum() == n - 12
        # given the record's length, the rows take its row (they cross an edge with it)
        rows_eom, keep = padded_rows([tuple(np.zeros(n - 12) for _ in range(4))], [n])
        assert rows_eom[0][0].shape == (row_bucket(n),) and keep.sum() == n - 12


def test_records_of_one_scene_share_their_layout():
    # Lab-rig records at 200 Hz (a period of 0.23 s, two to a segment, the counts of
    # `strategy.record_segments`): 5, 6 and 7 s records share one shape (single and
    # multiple shooting), 8, 10 and 12 s the next; the segments' rows have one length.
    counts = {5.0: 12, 6.0: 16, 7.0: 16, 8.0: 24, 10.0: 24, 12.0: 32, 16.0: 48, 20.0: 48}
    shapes = {t: (segment_layout(int(200 * t) + 1, S), segment_layout(int(200 * t) + 1, 1))
              for t, S in counts.items()}
    assert shapes[5.0] == shapes[6.0] == shapes[7.0] == ((16, 96), (1, 1536))
    assert shapes[8.0] == shapes[10.0] == shapes[12.0] == ((32, 96), (1, 3072))
    assert shapes[16.0] == shapes[20.0] == ((64, 96), (1, 6144))
    assert (row_bucket(1001), row_bucket(3001), row_bucket(3073)) == (1536, 3072, 6144)


def _counts_per_record(lab_rig, calls):
    """For two records of other lengths (101 and 106 samples: one row length) cut into 3
    and 4 segments (one class): JAX's traces and compiles while `calls(prob, ss, data)` ran
    on each (`prob` multiple shooting, `ss` single)."""
    runs = []
    for t1, seed, S in ((1.0, 1, 3), (1.05, 2, 4)):
        data = _record(lab_rig, t1, seed)
        prob, ss = _problem(lab_rig, data, S), _problem(lab_rig, data, 1)
        with counting() as counts:
            calls(prob, ss, data)
        runs.append(counts)
    return runs


def _start(ss):
    return ss.to_z([2.1, 0.0025, 1.0, 0.0])


@pytest.mark.full
def test_a_new_length_compiles_nothing(lab_rig):
    # The second record's programs are the first's: a trace counter sees no trace and no
    # compile for it, in the multiple-shooting residuals and the motion start's equation
    # of motion.
    def calls(prob, ss, data):
        r, failed, _ = residuals_at(prob, jnp.asarray(_z(prob, data)))
        assert int(failed) == 0 and np.all(np.isfinite(np.asarray(r)))
        assert motion_start(ss, _start(ss), [data], [data.phi], [0.23]) is not None

    first, second = _counts_per_record(lab_rig, calls)
    assert first[_COMPILE] > 0  # the counter sees compiles
    assert second == {_COMPILE: 0, _TRACE: 0}, second


@pytest.mark.full
def test_a_new_length_compiles_no_jacobian(lab_rig):
    # The same for the Jacobians, of multiple shooting and of single shooting.
    def calls(prob, ss, data):
        r, failed, _, _ = jacobian_at(prob, jnp.asarray(_z(prob, data)))
        assert int(failed) == 0 and np.all(np.isfinite(np.asarray(r)))
        jax.block_until_ready(jacobian_at(ss, jnp.asarray(_start(ss))))

    first, second = _counts_per_record(lab_rig, calls)
    assert first[_COMPILE] > 0
    assert second == {_COMPILE: 0, _TRACE: 0}, second


def _normal_equations(prob, z):
    """(J^T J, J^T r, r^T r) over the free coordinates (inactive rows' states held), and
    the steps the solves report."""
    r, failed, steps, J = (np.asarray(x) for x in jacobian_at(prob, jnp.asarray(z)))
    assert int(failed) == 0
    B = basis(np.eye(prob.p), prob.p + prob.n_extra, prob.state_on)
    Jw = J @ B
    return (Jw.T @ Jw, Jw.T @ r, r @ r), steps


@pytest.mark.full
def test_padding_changes_no_value(lab_rig):
    # 5 segments (8 rows: 3 inactive) and each row padded, against the record as it is:
    # the same cost, gradient and Gauss-Newton matrix to rounding, so the same LM steps.
    data = _record(lab_rig, 2.0, 3)
    padded, plain = _problem(lab_rig, data, 5), _problem(lab_rig, data, 5, pad=False)
    # (the continuity defects weigh as a padded row's worth of data: the same weight)
    plain = eqx.tree_at(lambda p: p.exps[0].seg.size, plain, padded.exps[0].seg.size)
    assert padded.exps[0].seg.ts.shape[0] == 8 and plain.exps[0].seg.ts.shape[0] == 5
    assert padded.n_residuals == plain.n_residuals == data.n
    zp = _z(padded, data)
    zq = np.concatenate([zp[:plain.p], zp[padded.p:][padded.state_on]])
    (a, steps_a), (b, steps_b) = _normal_equations(padded, zp), _normal_equations(plain, zq)
    for x, y in zip(a, b):
        np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-12 * np.max(np.abs(y)))
    # The padded save times repeat a row's last and take no step: the padded rows report
    # the plain rows' steps exactly (the count a fit judges, its step budget).
    np.testing.assert_array_equal(steps_a, steps_b)
    # So does single shooting, whose row of 384 holds 183 padded save times, and its
    # residuals are the plain row's to the bit.
    one, whole = _problem(lab_rig, data, 1), _problem(lab_rig, data, 1, pad=False)
    assert one.exps[0].seg.ts.shape == (1, 384)
    (r1, _, s1), (r2, _, s2) = (residuals_at(p, jnp.asarray(_start(p))) for p in (one, whole))
    assert int(s1[0]) == int(s2[0]), (s1, s2)
    np.testing.assert_array_equal(np.asarray(r1)[:data.n], np.asarray(r2))
    assert np.all(np.asarray(r1)[data.n:] == 0.0)


@contextlib.contextmanager
def _rows_unpadded():
    """Rows as long as their samples (a plain layout): the row ladder made the identity."""
    mp = pytest.MonkeyPatch()
    for module in (segments, start):
        mp.setattr(module, "row_bucket", lambda m: m)
    try:
        yield
    finally:
        mp.undo()


@pytest.mark.full
def test_a_record_across_the_old_bucket_edge_is_warm():
    # A 5 s lab record at 200 Hz (1001 samples, 12 segments), then a 6 s one (1201
    # samples, 16 segments): the rows pad to one ladder size, so the second fit traces and
    # compiles nothing; and its estimate is the fit's with rows as long as their samples.
    lab = cj.load_scene("lab-rig")
    begin = cj.Scene(lab.mech.replace(k=2.4, c=0.004), phi0=1.0, name="lab-rig-start")
    rec5, rec6 = (cj.synthesize(lab, t1=t1, rate=200.0, noise_std=1e-3, seed=seed)
                  for t1, seed in ((5.0, 1), (6.0, 2)))
    cj.fit(begin, rec5, progress=False)
    with counting() as counts:
        warm = cj.fit(begin, rec6, progress=False)
    assert counts == {_COMPILE: 0, _TRACE: 0}, counts
    assert warm.strategy.startswith("multiple shooting (16 segments)")
    with _rows_unpadded():
        plain = cj.fit(begin, rec6, progress=False)
    assert plain.converged and warm.converged
    for name in FREE:
        se = float(warm.stderr[name])
        assert abs(float(warm.values[name]) - float(plain.values[name])) <= 1e-8 * se, name
        np.testing.assert_allclose(float(warm.values[name]), float(plain.values[name]),
                                   rtol=1e-9, atol=0.0)
