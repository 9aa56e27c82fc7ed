"""Many independent fits at once (`crank_jax.fleet.fit_many`, `crank-jax fit --each`):
the fleet's estimates are the single fits', a failing record changes no other's result,
and the command writes one fit.json per record and a summary."""

import csv
import json

import numpy as np
import pytest
from conftest import experiment

import crank_jax as cj
from crank_jax.cli import main
from crank_jax.fleet import many as fm

# Three lab-rig records of slightly different lengths (one row length: 384 samples) and noise.
SPECS = ((1, 2.9, 1e-3), (2, 3.0, 2e-3), (3, 3.3, 1e-3))
FREE = ("k", "c", "phi0", "dphi0")


@pytest.fixture(scope="module")
def records(lab_rig):
    # One solve (one compile), then each record its own length and noise.
    clean = cj.synthesize(lab_rig, t1=max(t1 for _, t1, _ in SPECS), rate=100.0)
    out = []
    for seed, t1, ns in SPECS:
        d = clean.window(None, t1 + 1e-9)
        noise = np.random.default_rng(seed).normal(0.0, ns, d.ts.shape)
        out.append(cj.Data(ts=d.ts, phi=d.phi + noise))
    return out


@pytest.fixture(scope="module")
def fleet(lab_rig, records):
    return fm.fit_many(lab_rig, records, FREE, progress=False)


@pytest.mark.full
def test_fleet_equals_each_single_fit(lab_rig, records, fleet):
    assert fleet.alone == [None, None, None]  # every record fitted side by side
    assert len(fleet) == 3
    for d, res in zip(records, fleet):
        one = cj.fit(lab_rig, d, FREE, progress=False)
        assert res.converged and one.converged
        assert res.names == one.names and res.n_samples == one.n_samples
        for n in FREE:
            # Both stop at the same test (a step below 1/100 of a standard error).
            assert abs(res.values[n] - one.values[n]) <= one.stderr[n] / 20, n
            assert res.stderr[n] == pytest.approx(one.stderr[n], rel=1e-3)
        assert res.to_json().keys() == one.to_json().keys()
    rows = fleet.rows(["a", "b", "c"])
    assert [r["record"] for r in rows] == ["a", "b", "c"]
    assert rows[1]["k"] == fleet[1].values["k"] and rows[1]["k_stderr"] == fleet[1].stderr["k"]


def _members(lab_rig, records):
    kw = dict(init="scene", method="lm", shooting="auto", segments=None, multistart=1,
              seed=0, max_steps=None, tol=1e-8, sigma=None, profile=None, window=None,
              progress=False, warn=False, force=None, load_by="time")
    return {i: fm._plan(lab_rig, d, FREE, kw) for i, d in enumerate(records)}


@pytest.mark.full
def test_a_poisoned_record_leaves_the_others_bit_for_bit(lab_rig, records, fleet):
    import equinox as eqx

    members = _members(lab_rig, records)
    items = {i: (m.plan.shoot, m.plan.z0, m.noise) for i, m in members.items()}
    good, _ = fm._fleet(items, 1e-8, 100)
    assert sorted(good) == [0, 1, 2]
    for i, res in enumerate(fleet):  # the fleet's own results are fit_many's
        assert res.values["k"] == members[i].plan.single.host_values(good[i][0])[0]
    # NaN in one record's data, and a start that diverges (k 10^6 times too stiff).
    problem, z0, noise = items[1]
    ys = np.asarray(problem.exps[0].seg.ys).copy()
    ys[..., 40] = np.nan
    nan = (eqx.tree_at(lambda p: p.exps[0].seg.ys, problem, ys), z0, noise)
    far = (items[2][0], items[2][1] + np.array([np.log(1e6), 0, 0, 0]), items[2][2])
    out, left = fm._fleet({0: items[0], 1: nan, 2: items[2], 3: far}, 1e-8, 100)
    assert sorted(left) == [1, 3] and sorted(out) == [0, 2]
    clean, _ = fm._fleet({0: items[0], 2: items[2]}, 1e-8, 100)
    for i in (0, 2):
        assert all(np.array_equal(a, b) for a, b in zip(out[i], clean[i]))


@pytest.fixture(scope="module")
def rotating_member():
    """One record of the fleet bench's rotating rig (two channels, weighted by their
    noise), planned for single shooting: the fleet's member."""
    fr = experiment("fleet_rot")
    scene, recs = fr.records(1)
    kw = dict(init="scene", method="lm", shooting="single", segments=None, multistart=1,
              seed=0, max_steps=None, tol=1e-8, sigma=dict(fr.NOISE), profile=None,
              window=None, progress=False, warn=False, force=None, load_by="time")
    return fm._plan(scene, recs[0][0], fr.FREE, kw)


@pytest.mark.full
def test_a_start_near_the_minimum_takes_the_gauss_newton_step(rotating_member):
    # The rotating rig of the fleet bench (two channels, weighted by their noise), whose
    # column-scaled sensitivities have a singular value of 0.004 of the largest. One
    # standard error off the minimum in every coordinate the problem is linear to well
    # within the stop test: the Gauss-Newton step lands and the next point is judged
    # converged. A damped start (Nielsen's 1e-3 of the scaled normal matrix's diagonal,
    # then cut by at most 3 an accepted step) shrank the weak direction's step to 2% of
    # Gauss-Newton's and took 6 iterations here.
    from crank_jax.fleet.batch_lm import run_batch

    m = rotating_member
    out = run_batch([m.plan.single], [m.plan.z0], [m.noise], 1e-8, 100)
    assert fm.STATUS[int(out.status[0])] == "converged"
    z, J = out.z[0], out.J[0]
    se = m.noise * np.sqrt(np.diag(np.linalg.inv(J.T @ J)))
    for sign in (1, -1):
        out = run_batch([m.plan.single], [z + sign * se], [m.noise], 1e-8, 100)
        assert fm.STATUS[int(out.status[0])] == "converged"
        assert int(out.iterations[0]) <= 2, out.iterations
        assert np.all(np.abs(out.z[0] - z) <= se / 20)


@pytest.mark.full
def test_the_plans_overlapping_the_fits_change_no_result(lab_rig, records):
    # 20 records: two batches of one shape or more, the second planned while the first is
    # fitted. Each result equals, bit for bit, its batch fitted after every plan, on
    # this thread (the overlap changes the time, never a result).
    from crank_jax.fleet.batch_lm import largest_batch

    many = [cj.Data(ts=d.ts, phi=d.phi + np.random.default_rng(9 + k).normal(
        0.0, 1e-4, d.ts.shape)) for k in range(7) for d in records][:20]
    fleet = fm.fit_many(lab_rig, many, FREE, progress=False)
    assert fleet.alone == [None] * 20
    members = _members(lab_rig, many)
    groups: dict = {}
    for i, m in members.items():
        groups.setdefault(fm.shape_key(m.plan.shoot), []).append(i)
    assert max(map(len, groups.values())) > largest_batch()
    runs = {}
    for idx in groups.values():
        for k in range(0, len(idx), largest_batch()):
            part = idx[k:k + largest_batch()]
            runs.update(fm._fit_fleet({i: members[i] for i in part}, 1e-8, 100,
                                      fm.progress_bar(None, "", False))[0])
    for i, res in enumerate(fleet):
        single = members[i].plan.single
        assert [res.values[n] for n in single.names] == list(single.host_values(runs[i].z))


@pytest.mark.full
def test_two_threads_fitting_batches_at_once_both_finish(rotating_member):
    # Two compiled LM calls at once would each park an XLA:CPU intra-op thread in the
    # batched SVD's wait for its own work (a pool of two: both wait forever); the fleet
    # serialises them. Two threads' batches of one record each finish.
    import threading

    from crank_jax.fleet.batch_lm import run_batch

    m = rotating_member
    args = ([m.plan.single] * 4, [m.plan.z0] * 4, [m.noise] * 4, 1e-8, 100)
    alone = run_batch(*args)
    out = {}
    threads = [threading.Thread(target=lambda k=k: out.setdefault(k, run_batch(*args)),
                                daemon=True) for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert sorted(out) == [0, 1], "a batch did not finish within 120 s"
    for k in (0, 1):
        assert all(np.array_equal(a, b) for a, b in zip(out[k], alone))


@pytest.mark.full
def test_a_failing_start_solve_leaves_the_others_plans_alone(lab_rig, records):
    from crank_jax.fleet.batch_lm import start_solves
    from crank_jax.identify.fit_plan import start_solve

    members = _members(lab_rig, records)
    asks = [(m.plan.single, m.plan.single.to_z([m.plan.start[n] for n in m.plan.single.names]))
            for m in members.values()]
    side = start_solves(asks)  # side by side: each finite, each its own record's
    for (ss, z), row in zip(asks, side):
        alone = start_solve(ss, z)
        assert int(row[1]) == 0 and np.all(np.isfinite(row[3]))
        # (the records differ by their noise, 1e-3 rad: each row is its own record's)
        np.testing.assert_allclose(row[0], alone[0], rtol=0, atol=1e-7)
    # A start whose solve fails (NaN): every member is then solved by itself, so the
    # others' plans are bit for bit their own.
    ss, z = asks[1]
    out = start_solves([asks[0], (ss, np.where(np.arange(z.size) == 1, np.nan, z)), asks[2]])
    assert int(out[1][1]) > 0  # its solve failed
    for a, b in zip(out[0] + out[2], start_solve(*asks[0]) + start_solve(*asks[2])):
        assert np.array_equal(a, b)


@pytest.mark.full
def test_each_writes_a_fit_json_per_record_and_a_summary(tmp_path, records, fleet):
    paths = []
    for i, d in enumerate(records):
        paths.append(tmp_path / f"rec{i}.csv")
        cj.save_data(d, paths[-1])
    out = tmp_path / "fits"
    rc = main(["fit", *map(str, paths), "lab-rig", "--each", "--out", str(out), "--quiet",
               "--report", "fits.html"])
    assert rc == 0
    assert sorted(p.name for p in out.iterdir()) == ["fits.html", "rec0.json", "rec1.json",
                                                     "rec2.json", "summary.csv"]
    html = (out / "fits.html").read_text()
    assert html.count('<tr data-name="') == 3 and "3 of 3 records converged" in html
    assert f'title="{fleet[1].values["k"]!r}"' in html
    doc = json.loads((out / "rec1.json").read_text())
    assert doc.keys() == fleet[1].to_json().keys()
    assert doc["estimates"]["k"]["value"] == pytest.approx(fleet[1].values["k"], rel=1e-12)
    with (out / "summary.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [r["record"] for r in rows] == ["rec0.csv", "rec1.csv", "rec2.csv"]
    assert list(rows[0])[:5] == list(fm.SUMMARY_COLUMNS)
    assert float(rows[2]["c"]) == pytest.approx(fleet[2].values["c"], rel=1e-12)
    assert "c_stderr" in rows[0] and rows[0]["converged"] == "True"


def test_each_refuses_clashes_before_any_fit(tmp_path, capsys):
    a, b = tmp_path / "x" / "rec.csv", tmp_path / "y" / "rec.csv"
    for p in (a, b):
        p.parent.mkdir()
        p.write_text("t,phi\n0,0\n")
    assert main(["fit", str(a), str(b), "lab-rig", "--each", "--out", str(tmp_path / "o")]) == 2
    assert "both write rec.json" in capsys.readouterr().err
    f = tmp_path / "file"
    f.write_text("")
    assert main(["fit", str(a), "lab-rig", "--each", "--out", str(f)]) == 2
    assert "is a file" in capsys.readouterr().err
    assert main(["fit", str(a), "lab-rig", "--each"]) == 2
    assert "--each needs --out DIR" in capsys.readouterr().err
    assert main(["fit", str(a), "lab-rig", "--each", "--out", str(tmp_path / "o"),
                 "--multistart", "3"]) == 2
    assert "--multistart is not taken with --each" in capsys.readouterr().err
    assert main(["fit", str(a), "lab-rig", "--each", "--out", str(tmp_path / "o"),
                 "--report", "summary.csv"]) == 2
    assert "would clash with the results" in capsys.readouterr().err
    assert main(["fit", str(a), str(b), "lab-rig", "--out", "x.json"]) == 2
    err = capsys.readouterr().err
    assert "--each fits each record by itself" in err and err.count("\n") == 1


def test_fit_many_names_the_record_of_a_bad_request(lab_rig):
    ts = np.linspace(0.0, 1.0, 101)
    records = [cj.Data(ts=ts, phi=np.cos(2 * ts)), cj.Data(ts=ts, phi=np.cos(3 * ts))]
    with pytest.raises(ValueError, match=r"record 0: `free=` names unknown parameter"):
        fm.fit_many(lab_rig, records[:2], ("k", "nope"), progress=False)
    with pytest.raises(ValueError, match="one scene per record"):
        fm.fit_many([lab_rig], records[:2], progress=False)


def _stand_in(k, se, converged=True):
    """What the summary report reads of a fit's result, for a report without fits."""
    from types import SimpleNamespace

    return SimpleNamespace(names=("k", "c"), values={"k": k, "c": 0.002},
                           stderr={"k": se, "c": None if not converged else 1e-5},
                           converged=converged, identifiable=True if converged else None,
                           iterations=5, rms_residual=1e-3, message="ended budget",
                           warnings=["fit did not converge: ended budget"], data=[])


def test_the_summary_report_has_a_row_and_a_verdict_per_record(tmp_path):
    from crank_jax.report import write_fleet_report

    fleet = fm.FleetResult([_stand_in(2.01, 0.01), _stand_in(1.98, 0.02),
                            _stand_in(7.5, None, converged=False)],
                           [None, None, "its fleet run ended budget"], 1.5)
    path = tmp_path / "fits.html"
    write_fleet_report(fleet, path, labels=["a.csv", "b.csv", "c.csv"], command="x")
    html = path.read_text()
    assert html.count('<tr data-name="') == 3
    assert '<tr data-name="c.csv" class="bad">' in html and "did NOT converge" in html
    assert "2 of 3 records converged" in html and "2 records fitted side by side" in html
    assert 'title="2.01"' in html and "<svg" in html  # the spread figure
    # The summary over the converged records: median k of 2.01 and 1.98.
    assert "median 1.995" in html and list(tmp_path.iterdir()) == [path]
