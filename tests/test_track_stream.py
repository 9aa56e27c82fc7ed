"""Tracking a long record from its file: the chunked reader's checks, the streamed result
equal to the one from memory, the path written to disk, and memory bounded on a record of
2 million samples."""

import json
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest

import crank_jax as cj
from crank_jax.online import runner as runner_module
from crank_jax.online import track, track_stream
from crank_jax.records.chunked import RecordChunks
from crank_jax.records.table import DataError

jax.config.update("jax_enable_x64", True)

LAB = cj.load_scene("lab-rig")


def _write(path, ts, phi, header="t,phi"):
    np.savetxt(path, np.stack([ts, phi], 1), delimiter=",", header=header, comments="",
               fmt="%.17g")


def test_the_chunked_reader_reads_the_record_and_names_a_bad_line(tmp_path):
    ts = np.arange(10) * 0.01
    path = tmp_path / "r.csv"
    _write(path, ts, np.sin(ts))
    got = list(RecordChunks(path, ["phi"], rows=4))
    assert [t.size for t, _ in got] == [4, 4, 2]
    np.testing.assert_array_equal(np.concatenate([t for t, _ in got]), ts)
    np.testing.assert_array_equal(np.concatenate([y for _, y in got])[:, 0], np.sin(ts))
    np.save(tmp_path / "r.npy", np.stack([ts, np.sin(ts)], 1))
    npy = np.concatenate([y for _, y in RecordChunks(tmp_path / "r.npy", ["phi"], rows=3)])
    np.testing.assert_array_equal(npy[:, 0], np.sin(ts))
    lines = path.read_text().splitlines()
    # A time that goes back across a chunk's edge (line 7: the 6th sample), a non-number.
    back = lines[:6] + ["0.001,0.5"] + lines[7:]
    (tmp_path / "b.csv").write_text("\n".join(back) + "\n")
    with pytest.raises(DataError, match=r"line 7: time 0.001 does not increase"):
        list(RecordChunks(tmp_path / "b.csv", ["phi"], rows=4))
    bad = lines[:3] + ["0.02,abc"] + lines[4:]
    (tmp_path / "c.csv").write_text("\n".join(bad) + "\n")
    with pytest.raises(DataError, match=r"line 4: column 'phi': 'abc' is not a number"):
        list(RecordChunks(tmp_path / "c.csv", ["phi"], rows=4))
    with pytest.raises(DataError, match=r"missing column 'x_s'"):
        RecordChunks(path, ["x_s"])


def test_a_streamed_record_equals_the_tracked_one_and_writes_its_path(tmp_path, monkeypatch):
    # The record is shorter than the start's seconds: both start from the same samples.
    ts = np.arange(0.0, 6.0, 1 / 200)
    phi = np.asarray(cj.simulate(LAB.mech, 1.0, 0.0, ts).phi)
    phi = phi + np.random.default_rng(1).normal(0.0, 1e-3, ts.size)
    path = tmp_path / "rec.csv"
    _write(path, ts, phi)
    monkeypatch.setattr(runner_module, "CHUNK", 500)
    kw = dict(free=("k", "c"), start="scene", start_seconds=10.0, progress=False)
    whole = track(LAB, cj.Data(ts, phi, source=str(path)), **kw)
    out = tmp_path / "path.csv"
    streamed = track_stream(LAB, path, every=3, path_out=out, **kw)
    np.testing.assert_array_equal(streamed.t, whole.t[::3])
    for n in ("k", "c"):
        np.testing.assert_allclose(streamed.values[n], whole.values[n][::3], rtol=1e-12)
        np.testing.assert_allclose(streamed.stderr[n], whole.stderr[n][::3], rtol=1e-9)
    cols = np.loadtxt(out, delimiter=",", skiprows=1)
    assert cols.shape == (ts.size, 9)
    np.testing.assert_allclose(cols[:, 3], whole.values["k"], rtol=1e-11)
    np.testing.assert_allclose(cols[:, 6], whole.stderr["c"], rtol=1e-9)
    assert streamed.settings["stream"]["samples"] == ts.size


_PEAK = textwrap.dedent("""
    import json, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    import numpy as np
    import crank_jax as cj
    from crank_jax.online import track_stream

    def peak_mb():
        for line in open("/proc/self/status"):
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024

    lab = cj.load_scene("lab-rig")
    short, long_ = sys.argv[1], sys.argv[2]
    kw = dict(free=("k", "c"), start="scene", progress=False, every=1000)
    track_stream(lab, short, **kw)  # compiled, warm
    before = peak_mb()
    res = track_stream(lab, long_, **kw)
    print(json.dumps({"before": before, "after": peak_mb(), "kept": int(res.t.size),
                      "samples": res.settings["stream"]["samples"]}))
""")


@pytest.mark.full
def test_memory_is_bounded_on_a_long_streamed_record(tmp_path):
    # 2 million samples (2.8 h at 200 Hz): a free decay, then the rig at rest, 1 mrad noise.
    n = 2_000_000
    ts = np.arange(n) / 200.0
    phi = np.zeros(n)
    phi[:4000] = np.asarray(cj.simulate(LAB.mech, 1.0, 0.0, ts[:4000]).phi)
    phi += np.random.default_rng(0).normal(0.0, 1e-3, n)
    _write(tmp_path / "short.csv", ts[:8000], phi[:8000])
    _write(tmp_path / "long.csv", ts, phi)
    del ts, phi
    run = subprocess.run([sys.executable, "-c", _PEAK, str(tmp_path / "short.csv"),
                          str(tmp_path / "long.csv")], capture_output=True, text=True,
                         timeout=1800)
    assert run.returncode == 0, run.stderr[-2000:]
    got = json.loads(run.stdout.strip().splitlines()[-1])
    assert got["samples"] == n and got["kept"] == n // 1000
    # The per-sample outputs of 2e6 samples (state, standard errors, innovations, the test)
    # are 12 float64 a sample, 192 MB; the record's two columns another 32 MB. The peak
    # grows by far less: the chunk, the kept path.
    assert got["after"] - got["before"] < 40.0, got
    print(f"peak growth {got['after'] - got['before']:.1f} MB")
