"""Issue 10: every hostile input a user can give gets one line and exit 2 (or 1 for a run
that could not finish), options are checked before any work, memory is bounded, signals
leave no temporary file, outputs get the umask's permissions and CSV reads as pandas reads
it. One test (or more) per row of the issue."""

import os
import signal
import stat
import subprocess
import sys
import time
from collections import namedtuple
from pathlib import Path

import numpy as np
import pytest

import crank_jax as cj
import crank_jax.cli.simulate_command as cli_simulate
import crank_jax.records.data as cj_data
import crank_jax.records.table as cj_table
import crank_jax.runtime.io as cj_io
import crank_jax.runtime.progress as progress
import crank_jax.scene as cj_scene
from crank_jax.cli import main

_Usage = namedtuple("_Usage", "total used free")


def _run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _one_line(err):
    lines = [ln for ln in err.strip().splitlines() if not ln.startswith("simulate:")]
    return len(lines) == 1 and "Traceback" not in err


@pytest.fixture
def scene_file(tmp_path):
    p = tmp_path / "s.toml"
    cj.save_scene(cj.load_scene("lab-rig"), p)
    return p


@pytest.fixture
def spy_simulate(monkeypatch):
    """Record the length of every `Scene.simulate` call; `calls[i]` is its sample count."""
    calls = []
    real = cj.Scene.simulate

    def spy(self, ts=None, **kw):
        calls.append(None if ts is None else len(ts))
        return real(self, ts, **kw)

    monkeypatch.setattr(cj.Scene, "simulate", spy)
    return calls


# --- rows 2 and 3: scene values that used to raise OverflowError / TypeError -------------

def _edit_scene(path, old, new):
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))


def test_row2_huge_integer_in_scene(scene_file, capsys):
    _edit_scene(scene_file, "k = ", "k = " + "9" * 400 + "\n#")
    before = scene_file.read_bytes()
    code, _, err = _run(capsys, "linearize", scene_file)
    assert code == 2 and _one_line(err) and "[mechanism] k must be finite" in err
    assert scene_file.read_bytes() == before


@pytest.mark.parametrize("extras", ["[[1]]", "[{a = 1}]", "[1]", '"energy"', '["energy", 2]'])
def test_row3_malformed_extras(scene_file, capsys, extras):
    _edit_scene(scene_file, "extras = []", f"extras = {extras}")
    code, _, err = _run(capsys, "linearize", scene_file)
    assert code == 2 and _one_line(err) and "[output] extras must be a list" in err


# --- rows 6 and 7: sizes are bounded; long runs stream in chunks --------------------------

@pytest.mark.parametrize("samples", ["100000000000", "9" * 400,
                                     str(cli_simulate.MAX_SAMPLES + 1)])
def test_row6_samples_beyond_the_limit_refused_before_work(tmp_path, capsys, spy_simulate,
                                                           samples):
    out = tmp_path / "x.csv"
    code, _, err = _run(capsys, "simulate", "lab-rig", "--samples", samples, "--out", out)
    assert code == 2 and _one_line(err) and str(cli_simulate.MAX_SAMPLES) in err
    assert spy_simulate == [] and not list(tmp_path.iterdir())


def test_row6_scene_samples_beyond_the_limit(scene_file, tmp_path, capsys, spy_simulate):
    _edit_scene(scene_file, "samples = ", "samples = 1" + "0" * 30 + "\n#")
    code, _, err = _run(capsys, "simulate", scene_file, "--out", tmp_path / "x.csv")
    assert code == 2 and _one_line(err) and "[output] samples" in err and spy_simulate == []


def test_row7_refused_when_the_disk_cannot_hold_it(tmp_path, capsys, monkeypatch, spy_simulate):
    monkeypatch.setattr(cli_simulate.shutil, "disk_usage", lambda p: _Usage(10**9, 0, 10**8))
    code, _, err = _run(capsys, "simulate", "lab-rig", "--samples", "300000000", "--t1", "1",
                        "--out", tmp_path / "x.csv")
    assert code == 2 and _one_line(err) and "GB free" in err
    assert spy_simulate == [] and not list(tmp_path.iterdir())


def test_row7_long_runs_stream_in_bounded_chunks(tmp_path, capsys, monkeypatch, spy_simulate):
    monkeypatch.setattr(cli_simulate, "CHUNK_SAMPLES", 40)
    # stderr is not a terminal here: progress comes as a line every LOG_INTERVAL s, and
    # this run is shorter than the default 5 s (the check held only on a slow machine).
    monkeypatch.setattr(progress, "LOG_INTERVAL", 0.0)
    out, png = tmp_path / "x.csv", tmp_path / "x.png"
    code, _, err = _run(capsys, "simulate", "lab-rig", "--t1", "2", "--samples", "201",
                        "--extras", "energy", "--out", out, "--plot", png)
    assert code == 0, err
    assert "simulate:" in err  # the progress bar, on stderr
    assert len(spy_simulate) == 5 and max(spy_simulate) == 41  # memory: one chunk at a time
    data = np.loadtxt(out, delimiter=",", skiprows=1)
    np.testing.assert_array_equal(data[:, 0], np.linspace(0, 2, 201))
    scene = cj.load_scene("lab-rig")
    ref = scene.simulate(np.linspace(0, 2, 201), outputs=("energy",), solver="dopri8",
                         rtol=1e-13, atol=1e-15)
    # Each chunk restarts the solver from the last state: the same solution to tolerance.
    # The default solver controls the local error per step at the default rtol 1e-8 (its
    # global error on the lab rig is ~1-2e-8 of each component's scale), so each solution,
    # chunked or not, is compared with a tight reference at twice that.
    one = scene.simulate(np.linspace(0, 2, 201))
    for phi, dphi in ((data[:, 1], data[:, 2]), (one.phi, one.dphi)):
        np.testing.assert_allclose(phi, ref.phi, rtol=0, atol=2e-8 * np.max(np.abs(ref.phi)))
        np.testing.assert_allclose(dphi, ref.dphi, rtol=0,
                                   atol=2e-8 * np.max(np.abs(ref.dphi)))
    np.testing.assert_allclose(data[:, 3], ref.extras["energy"], rtol=1e-7)
    assert png.stat().st_size > 1000


def test_synth_record_too_long_refused(tmp_path, capsys, spy_simulate):
    code, _, err = _run(capsys, "synth", "lab-rig", "--rate", "1e12", "--out", tmp_path / "d.csv")
    assert code == 2 and _one_line(err) and str(cj_data.MAX_RECORD_SAMPLES) in err
    assert spy_simulate == []


# --- row 8: every option is checked before any work --------------------------------------

@pytest.mark.parametrize("argv", [
    ["simulate", "lab-rig", "--t1", "0.1", "--samples", "3", "--plot", "p.xyz"],
    ["fit", "d.csv", "lab-rig", "--plot", "p.xyz"],
    ["demo", "--plot", "p.xyz"],
    ["demo", "--out", "nodir/r.json"],
    ["simulate", "lab-rig", "--out", "nodir/x.csv"],
    ["simulate", "lab-rig", "--plot", "nodir/x.png"],
    ["simulate", "lab-rig", "--out", "."],
    ["simulate", "lab-rig", "--out", "x.csv", "--plot", "x.csv"],
    ["synth", "lab-rig", "--out", "nodir/d.csv"],
])
def test_row8_options_checked_before_any_work(tmp_path, capsys, monkeypatch, spy_simulate, argv):
    monkeypatch.chdir(tmp_path)
    cj.save_data(cj.Data(np.arange(6.0), np.zeros(6)), "d.csv")
    if "--out" not in argv:
        argv = argv + ["--out", "x.csv"]
    t = time.perf_counter()
    code, _, err = _run(capsys, *argv)
    assert code == 2 and _one_line(err), err
    assert spy_simulate == [] and time.perf_counter() - t < 20
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.csv"]


def test_read_only_output_and_directory_refused(tmp_path, capsys):
    ro = tmp_path / "ro.csv"
    ro.write_text("keep\n")
    ro.chmod(0o444)
    if os.access(ro, os.W_OK):
        pytest.skip("running as root: a read-only file is still writable")
    code, _, err = _run(capsys, "simulate", "lab-rig", "--out", ro)
    assert code == 2 and "read-only" in err and ro.read_text() == "keep\n"


def test_dev_null_is_written_not_replaced(capsys):
    code, _, err = _run(capsys, "simulate", "lab-rig", "--t1", "0.1", "--samples", "3",
                        "--out", os.devnull)
    assert code == 0, err
    assert stat.S_ISCHR(os.stat(os.devnull).st_mode)


def test_symlink_output_written_through(tmp_path, capsys):
    target = tmp_path / "real.csv"
    target.write_text("old\n")
    link = tmp_path / "link.csv"
    link.symlink_to(target)
    code, _, err = _run(capsys, "simulate", "lab-rig", "--t1", "0.1", "--samples", "3",
                        "--out", link)
    assert code == 0, err
    assert link.is_symlink() and target.read_text().startswith("t,phi,dphi\n")


# --- rows 10 and 11 (and CRLF, UTF-16, decimal commas): CSV read as pandas reads it -------

_ROWS = [(0.1 * i, 0.5 * float(np.cos(i))) for i in range(6)]


def _table(sep=",", quote=False, eol="\n", dec="."):
    q = (lambda s: f'"{s}"') if quote else (lambda s: s)
    lines = [sep.join([q("t"), q("phi"), q("note")])]
    lines += [sep.join([f"{t!r}".replace(".", dec), f"{p!r}".replace(".", dec), q("a b")])
              for t, p in _ROWS]
    return eol.join(lines) + eol


@pytest.mark.parametrize("name,raw", [
    ("utf-8 bom (row 10)", b"\xef\xbb\xbf" + _table().encode()),
    ("quoted header (row 11)", _table(quote=True).encode()),
    ("crlf", _table(eol="\r\n").encode()),
    ("bom+quoted+crlf", b"\xef\xbb\xbf" + _table(quote=True, eol="\r\n").encode()),
    ("utf-16", _table().encode("utf-16")),
    ("semicolon, decimal comma", _table(sep=";", dec=",").encode()),
])
def test_rows10_11_csv_dialects(tmp_path, name, raw):
    p = tmp_path / "d.csv"
    p.write_bytes(raw)
    d = cj.load_data(p)
    np.testing.assert_array_equal(d.ts, [t for t, _ in _ROWS])
    np.testing.assert_array_equal(d.phi, [p for _, p in _ROWS])
    assert p.read_bytes() == raw


def test_header_that_is_data_says_so(tmp_path):
    p = tmp_path / "d.csv"
    p.write_text("".join(f"{t},{ph}\n" for t, ph in _ROWS))
    with pytest.raises(cj.DataError, match="line 1 is data, not a header"):
        cj.load_data(p)


def test_record_too_long_refused(tmp_path, monkeypatch):
    monkeypatch.setattr(cj_table, "MAX_RECORD_SAMPLES", 10)
    p = tmp_path / "d.csv"
    p.write_text("t,phi\n" + "".join(f"{i},0\n" for i in range(11)))
    with pytest.raises(cj.DataError, match="more than 10 samples"):
        cj.load_data(p)


# --- rows 18 and 19: signals leave no temporary file and never touch an existing output ---

def _tmp_files(d):
    return [p.name for p in d.iterdir() if p.name.endswith(".tmp")]


def _signal_on_third_chunk(monkeypatch, sig, before=lambda: None) -> list:
    """Make `crank-jax simulate` run in chunks of 20 samples and send this process `sig`
    as the third chunk starts (after `before()`); returns the list of chunk calls."""
    monkeypatch.setattr(cli_simulate, "CHUNK_SAMPLES", 20)
    real, calls = cj.Scene.simulate, []

    def spy(self, ts=None, **kw):
        calls.append(1)
        if len(calls) == 3:
            before()
            os.kill(os.getpid(), sig)
        return real(self, ts, **kw)

    monkeypatch.setattr(cj.Scene, "simulate", spy)
    return calls


@pytest.fixture
def usual_signals():
    """Python's usual dispositions of SIGINT, SIGHUP and SIGTERM for the test, restored
    after it. A process started in the background by a non-interactive shell inherits
    SIGINT ignored (as `nohup` ignores SIGHUP), and the CLI rightly keeps an ignored signal
    ignored (`test_an_ignored_signal_stays_ignored`)."""
    usual = {signal.SIGINT: signal.default_int_handler, signal.SIGHUP: signal.SIG_DFL,
             signal.SIGTERM: signal.SIG_DFL}
    old = {s: signal.signal(s, h) for s, h in usual.items()}
    yield
    for s, h in old.items():
        signal.signal(s, h)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGHUP, signal.SIGTERM])
def test_rows18_19_signal_mid_run_in_process(tmp_path, capsys, monkeypatch, sig,
                                             usual_signals):
    out = tmp_path / "big.csv"
    out.write_text("old\n")

    def before():
        assert _tmp_files(tmp_path)  # the output is being written

    calls = _signal_on_third_chunk(monkeypatch, sig, before)
    handlers = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGHUP)}
    code, _, err = _run(capsys, "simulate", "lab-rig", "--t1", "1", "--samples", "201",
                        "--out", out)
    assert code == 128 + sig and len(calls) == 3
    assert out.read_text() == "old\n" and _tmp_files(tmp_path) == []
    assert "Traceback" not in err
    assert handlers == {s: signal.getsignal(s) for s in handlers}  # handlers restored


def test_an_ignored_signal_stays_ignored(tmp_path, capsys, monkeypatch, usual_signals):
    # Under `nohup` (SIGHUP ignored) the run goes on and writes its output; the CLI's
    # handlers are removed afterwards and the signal is ignored again.
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    out = tmp_path / "out.csv"
    calls = _signal_on_third_chunk(monkeypatch, signal.SIGHUP)
    code, _, err = _run(capsys, "simulate", "lab-rig", "--t1", "1", "--samples", "201",
                        "--out", out)
    assert code == 0 and len(calls) == 10, err
    assert len(out.read_text().splitlines()) == 202  # the header and every sample
    assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN


def test_rows18_19_sigterm_real_process(tmp_path):
    out = tmp_path / "big.csv"
    out.write_text("old\n")
    env = dict(os.environ, CRANK_JAX_NO_CACHE="1")
    p = subprocess.Popen([sys.executable, "-m", "crank_jax", "simulate", "lab-rig", "--t1", "100",
                          "--samples", "5000000", "--out", str(out), "--quiet"],
                         stderr=subprocess.PIPE, text=True, env=env)
    try:
        deadline = time.monotonic() + 240
        while not _tmp_files(tmp_path) and p.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        assert _tmp_files(tmp_path), "the run never started writing"
        time.sleep(1.0)
        p.send_signal(signal.SIGTERM)
        _, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 128 + signal.SIGTERM, err
    assert "Traceback" not in err and "terminated by SIGTERM" in err
    assert out.read_text() == "old\n" and _tmp_files(tmp_path) == []


# --- row 20: outputs get the umask's permissions ------------------------------------------

def test_row20_outputs_follow_the_umask(tmp_path, capsys):
    old = os.umask(0o027)
    try:
        code, _, err = _run(capsys, "simulate", "lab-rig", "--t1", "0.1", "--samples", "3",
                            "--out", tmp_path / "x.csv")
        cj.save_data(cj.Data(np.arange(6.0), np.zeros(6)), tmp_path / "d.csv")
        cj.save_scene(cj.load_scene("lab-rig"), tmp_path / "s.toml")
        np.savetxt(tmp_path / "np.csv", np.zeros(2))
    finally:
        os.umask(old)
    assert code == 0, err
    for name in ("x.csv", "d.csv", "s.toml"):
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == 0o640, name
    assert stat.S_IMODE((tmp_path / "np.csv").stat().st_mode) == 0o640  # as numpy does
    # An existing file keeps its mode, as open(path, "w") keeps it.
    (tmp_path / "x.csv").chmod(0o600)
    code, _, _ = _run(capsys, "simulate", "lab-rig", "--t1", "0.1", "--samples", "3",
                      "--out", tmp_path / "x.csv")
    assert code == 0 and stat.S_IMODE((tmp_path / "x.csv").stat().st_mode) == 0o600


# --- no traceback for any exception class ---------------------------------------------------

@pytest.mark.parametrize("exc,code", [
    (TypeError("unhashable type: 'list'"), 1), (OverflowError("int too large"), 1),
    (ZeroDivisionError("division by zero"), 1), (MemoryError(), 1),
    (RuntimeError("max_steps reached"), 1), (ValueError("bad value\nmore"), 2),
    (PermissionError(13, "Permission denied"), 2),
])
def test_no_traceback_for_any_exception(capsys, monkeypatch, exc, code):
    def boom(a):
        raise exc

    monkeypatch.setattr(cli_simulate, "COMMANDS",
                        [(n, h, add, boom) for n, h, add, _ in cli_simulate.COMMANDS])
    got, _, err = _run(capsys, "scenes")
    assert got == code and _one_line(err) and err.startswith("crank-jax: error: ")
    got, _, err = _run(capsys, "scenes", "--debug")
    assert got == code and "Traceback" in err
    monkeypatch.setenv("CRANK_JAX_DEBUG", "1")
    got, _, err = _run(capsys, "scenes")
    assert got == code and "Traceback" in err


def test_binary_or_endless_data_file_refused_quickly(tmp_path, capsys):
    p = tmp_path / "d.csv"
    p.write_bytes(b"\x00" * 200_000)
    with pytest.raises(cj.DataError, match="line 1 is longer than"):
        cj.load_data(p)
    code, _, err = _run(capsys, "fit", "/dev/zero", "lab-rig")  # refused unopened (issue 24)
    assert code == 2 and _one_line(err) and "character device, not a regular file" in err


@pytest.mark.parametrize("value", ["1.3407807929942597e+154", "1e-300", "-1e31"])
def test_scene_numbers_beyond_float64_products_refused(scene_file, capsys, value):
    # Found by test_properties: s = sqrt(max float) made m_c s^2 overflow.
    _edit_scene(scene_file, "s = ", f"s = {value}\n#")
    code, _, err = _run(capsys, "linearize", scene_file)
    assert code == 2 and _one_line(err) and "[mechanism] s = " in err and "out of range" in err


def test_warnings_are_one_line(capsys, monkeypatch):
    import warnings

    def warn(a):
        warnings.warn("something odd\nsecond line", UserWarning, stacklevel=1)
        return 0

    monkeypatch.setattr(cli_simulate, "COMMANDS",
                        [(n, h, add, warn) for n, h, add, _ in cli_simulate.COMMANDS])
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        code, _, err = _run(capsys, "scenes")
    assert code == 0 and err == "crank-jax: warning: something odd\n"


@pytest.mark.parametrize("argv, needle", [
    (("--phi0", "1e300"), "turns from rest"),
    (("--dphi0", "1e12"), "turns from rest"),
    (("--rtol", "1e-300"), "rtol must be"),
])
def test_absurd_start_or_tolerance_refused_at_once(tmp_path, capsys, argv, needle):
    """Finite but absurd initial states and tolerances: exit 2, one line, before a solve
    (they used to run ~20 s and exit 1, or be accepted)."""
    out = tmp_path / "x.csv"
    t = time.perf_counter()
    code, _, err = _run(capsys, "simulate", "lab-rig", *argv, "--out", out)
    assert code == 2 and _one_line(err) and needle in err, err
    assert not out.exists() and time.perf_counter() - t < 10


def test_signal_noted_when_its_exception_is_dropped(tmp_path, monkeypatch):
    """Python drops an exception raised by a signal handler while a gc callback runs (JAX
    has one), so the run went on and replaced the output: the noted signal stops the
    commit, and main exits with the signal's status."""
    io = cj_io
    out = tmp_path / "o.txt"
    out.write_text("old\n")
    io.note_signal(signal.SIGTERM)
    try:
        with pytest.raises(io.Terminated), io.atomic_write(out) as f:
            f.write("new\n")
    finally:
        io.note_signal(None)
    assert out.read_text() == "old\n" and _tmp_files(tmp_path) == []


def test_main_exits_with_a_dropped_signal(capsys, monkeypatch):
    cli_main = sys.modules["crank_jax.cli.main"]  # (crank_jax.cli.main is also the function)

    def dropped(args):  # a command during which the handler's exception was dropped
        cj_io.note_signal(signal.SIGTERM)
        return 0

    build = cli_main.build_parser

    def parser_with(run):
        parser = build()
        parser.set_defaults(_run=run)
        for action in parser._subparsers._group_actions:
            for sub in action.choices.values():
                sub.set_defaults(_run=run)
        return parser

    monkeypatch.setattr(cli_main, "build_parser", lambda: parser_with(dropped))
    code, _, err = _run(capsys, "scenes")
    assert code == 128 + signal.SIGTERM and "terminated by SIGTERM" in err


def test_huge_scene_file_refused_before_reading(tmp_path, monkeypatch):
    big = tmp_path / "big.toml"
    big.write_bytes(b"# " + b"x" * (cj_scene.MAX_SCENE_BYTES + 10) + b"\n")
    monkeypatch.setattr(Path, "read_text", lambda *a, **k: pytest.fail("read"))
    with pytest.raises(cj.SceneError, match="not a scene file"):
        cj.load_scene(big)


def test_a_lazy_module_is_whole_when_two_threads_touch_it_at_once(tmp_path, monkeypatch):
    # lazy.py imports diffrax and optax on first use. Two threads touching such a module
    # at once must both see it fully imported (the standard library's LazyLoader, before
    # Python 3.12, let the second see it half executed). A module that takes 0.3 s to
    # import keeps the first thread inside the import while the second arrives.
    import sys
    import threading

    from crank_jax.runtime.lazy import lazy_import

    (tmp_path / "slow_module_for_lazy_test.py").write_text(
        "import time\ntime.sleep(0.3)\nVALUE = 42\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "slow_module_for_lazy_test", raising=False)
    mod = lazy_import("slow_module_for_lazy_test")
    seen, errors = [], []

    def touch():
        try:
            seen.append(mod.VALUE)
        except Exception as e:  # noqa: BLE001 (the failure this test looks for)
            errors.append(repr(e))

    threads = [threading.Thread(target=touch) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and seen == [42, 42]
    with pytest.raises(ModuleNotFoundError):
        lazy_import("no_such_module_for_lazy_test")
