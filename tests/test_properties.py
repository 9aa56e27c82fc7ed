"""Property-based tests (hypothesis) of the command line's contract, issue 10.

Over generated scene files, CSV records and command lines, `crank_jax.cli.main(argv)`
(run in-process: a subprocess would pay ~2 s of JAX import per example):

- exits 0 or 2; 1 only for a run that could not finish, with its one-line reason;
- never prints a traceback; a failure is exactly one line on stderr;
- leaves every input file byte-identical, and an existing output untouched on failure;
- leaves no temporary file, and writes no NaN or inf into any output.

Input classes covered (see each strategy): scene files with any TOML value in any known or
unknown table/key (huge and negative integers, NaN/inf floats, booleans, strings, nested
arrays and inline tables), missing keys and tables, non-table tables, garbage text and
non-UTF-8 bytes; CSV records in every dialect (UTF-8/UTF-16 byte-order marks, quoted
names and values, CRLF/CR line ends, comma/semicolon/whitespace separators, decimal
commas, comments, extra columns) with hostile cells (NaN, inf, huge, empty, text,
repeated or decreasing times, ragged rows, too few rows); and command lines mixing valid
values with hostile ones (non-numbers, NaN, inf, 1e400, zero, negatives, huge integers,
unknown names, outputs that are directories, inputs, missing directories, /dev/null,
unsupported plot formats).

**Budget.** CI runs a few examples per property (this file < 60 s on 2 cores). For a
thorough run set `CRANK_JAX_PROPERTY_EXAMPLES`, e.g.

    CRANK_JAX_PROPERTY_EXAMPLES=2000 pytest tests/test_properties.py

which also draws fresh random inputs (CI is derandomized, so it is reproducible).
"""

import json
import math
import os
import tempfile
import tomllib
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

import crank_jax as cj
from crank_jax.cli import main
from crank_jax.records.data import MIN_SAMPLES

_EXAMPLES = int(os.environ.get("CRANK_JAX_PROPERTY_EXAMPLES", "0"))


def _budget(ci: int):
    """Hypothesis settings: `ci` examples, derandomized, unless a budget is set."""
    checks = [HealthCheck.too_slow, HealthCheck.function_scoped_fixture,
              HealthCheck.data_too_large]  # capsys is read (and so reset) every example
    return settings(max_examples=_EXAMPLES or ci, derandomize=not _EXAMPLES, deadline=None,
                    database=None, suppress_health_check=checks)


def _snapshot(d: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in d.iterdir() if p.is_file()}


def _check_contract(argv, d: Path, inputs: list[str], capsys) -> tuple[int, str]:
    """Run the CLI and assert the contract; return (exit code, stderr)."""
    before = _snapshot(d)
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    event(f"{argv[0]}: exit {code}")  # see --hypothesis-show-statistics
    assert "Traceback" not in err, err
    assert code in (0, 1, 2), (code, err)
    if code == 1:  # only a run that could not finish, never a crash of ours
        assert "maximum number of solver steps" in err, err
    lines = [ln for ln in err.strip().splitlines() if not ln.startswith(("simulate:", "\r"))]
    if code != 0:
        assert len(lines) == 1 and lines[0].startswith("crank-jax: error: "), err
    after = _snapshot(d)
    for name in inputs:
        assert after[name] == before[name], f"input {name} changed"
    assert not [n for n in after if n.endswith(".tmp")], "temporary file left behind"
    for name, data in after.items():
        if name in before and code != 0:
            assert data == before[name], f"{name} touched by a failed run"
        if name not in before or data != before[name]:
            if name.endswith((".csv", ".json")):
                text = data.decode().lower()
                assert "nan" not in text and "inf" not in text, f"{name}: {text[:200]}"
    return code, err


# --- scene files ------------------------------------------------------------------------------

_LAB = tomllib.loads(cj.scene_to_toml(cj.load_scene("lab-rig")))
_TABLES = {t: list(v) for t, v in _LAB.items() if isinstance(v, dict)}
_TABLES.update(load=["P0", "P1", "freq_hz", "phase"], torque=["tau0", "tau1", "freq_hz"])

_text = st.text(st.characters(blacklist_categories=("Cs",)), max_size=8)
_scalar = st.one_of(
    st.integers(), st.integers(min_value=-10**500, max_value=10**500),
    st.floats(), st.floats(min_value=-1e3, max_value=1e3), st.booleans(), _text,
    st.sampled_from(["energy", "reactions", "tsit5", "kvaerno5", "bogus"]),
)
_value = st.recursive(_scalar, lambda inner: st.one_of(
    st.lists(inner, max_size=3), st.dictionaries(st.sampled_from(["a", "k", "x"]), inner,
                                                 max_size=2)), max_leaves=5)


def _toml(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return ("nan" if math.isnan(v) else ("inf" if v > 0 else "-inf")) \
            if not math.isfinite(v) else repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    return "{" + ", ".join(f"{json.dumps(k)} = {_toml(x)}" for k, x in v.items()) + "}"


def _doc_to_toml(doc: dict) -> str:
    lines = [f"{json.dumps(k)} = {_toml(v)}" for k, v in doc.items() if not isinstance(v, dict)]
    for t, body in doc.items():
        if isinstance(body, dict):
            lines.append(f"[{json.dumps(t)}]")
            lines += [f"{json.dumps(k)} = {_toml(v)}" for k, v in body.items()]
    return "\n".join(lines) + "\n"


@st.composite
def scene_texts(draw) -> bytes:
    doc = json.loads(json.dumps(_LAB))
    for _ in range(draw(st.integers(0, 3))):
        kind = draw(st.sampled_from(["set", "set", "set", "delete", "table", "unknown"]))
        table = draw(st.sampled_from(sorted(_TABLES)))
        key = draw(st.sampled_from(_TABLES[table]))
        if not isinstance(doc.get(table, {}), dict):
            doc[table] = {}
        if kind == "set":
            doc.setdefault(table, {})[key] = draw(_value)
        elif kind == "delete":
            doc.get(table, {}).pop(key, None)
        elif kind == "table":
            doc[table] = draw(_scalar)
        else:
            doc[draw(st.sampled_from([table, "extra"]))] = {draw(_text) or "z": 1}
    text = _doc_to_toml(doc).encode()
    if draw(st.booleans()):
        text = b"\xef\xbb\xbf" + text  # a UTF-8 byte-order mark is not an error
    garbage = draw(st.sampled_from(["none", "none", "none", "text", "bytes"]))
    if garbage != "none":
        at = draw(st.integers(0, len(text)))
        junk = draw(_text).encode() if garbage == "text" else draw(st.binary(max_size=8))
        text = text[:at] + junk + text[at:]
    return text


@_budget(60)
@given(scene_texts())
def test_any_scene_file(capsys, text):
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        (d / "s.toml").write_bytes(text)
        code, err = _check_contract(["linearize", d / "s.toml", "--json"], d, ["s.toml"],
                                    capsys)
        assert code in (0, 2), err
        if text.startswith(b"\xef\xbb\xbf"):  # the mark changes nothing
            (d / "plain.toml").write_bytes(text[3:])
            try:
                cj.load_scene(d / "plain.toml")
            except cj.SceneError:
                assert code == 2
            else:
                assert code == 0, err


# --- CSV records ------------------------------------------------------------------------------

_cell = st.one_of(
    st.floats(allow_nan=False, allow_infinity=False, width=64).map(repr),
    st.sampled_from(["nan", "inf", "-inf", "", "x", "1e400", '"1.5"', "1,5", " 2 ", "0x10"]),
)


@st.composite
def csv_files(draw) -> tuple[bytes, bool]:
    """(file bytes, whether the record is valid as drawn)."""
    n = draw(st.integers(0, 9))
    extra = draw(st.booleans())
    ts = np.cumsum(draw(st.lists(st.floats(1e-3, 10), min_size=n, max_size=n))).tolist()
    phi = draw(st.lists(st.floats(-1e3, 1e3), min_size=n, max_size=n))
    rows = [[repr(t), repr(p)] + (["a b"] if extra else []) for t, p in zip(ts, phi)]
    valid = n >= MIN_SAMPLES
    if n and draw(st.booleans()):  # spoil one cell, or one row's length, or the order
        i = draw(st.integers(0, n - 1))
        how = draw(st.sampled_from(["cell", "ragged", "swap"]))
        if how == "cell":
            rows[i][draw(st.integers(0, 1))] = draw(_cell)
        elif how == "ragged":
            rows[i] = rows[i][:-1] if draw(st.booleans()) else rows[i] + ["7"]
        elif i > 0:
            rows[i][0], rows[i - 1][0] = rows[i - 1][0], rows[i][0]
        valid = False
    names = draw(st.sampled_from([["t", "phi"], ["time", "phi"], ["t", "t"], ["t", "phi "]]))
    if names != ["t", "phi"] and names != ["t", "phi "]:
        valid = False
    header = names + (["note"] if extra else [])
    sep = draw(st.sampled_from([",", ";", " ", "\t"]))
    quote = draw(st.booleans()) and sep in ",;"
    q = (lambda s: f'"{s}"') if quote else (lambda s: s)
    if sep in " \t":
        header = [h.replace(" ", "") for h in header]
        rows = [[c.replace(" ", "") or "x" for c in r] for r in rows]
        if extra:
            rows = [r[:-1] + ["ab"] for r in rows]
    if sep == ";" and draw(st.booleans()):
        rows = [[c.replace(".", ",") for c in r] for r in rows]  # decimal commas
    eol = draw(st.sampled_from(["\n", "\r\n", "\r"]))
    lines = draw(st.sampled_from([[], ["# logged by rig 3"], ["% matlab"]]))
    lines += [sep.join(q(h) for h in header)] + [sep.join(q(c) for c in r) for r in rows]
    text = eol.join(lines) + eol
    enc = draw(st.sampled_from(["utf-8", "utf-8-sig", "utf-16"]))
    return text.encode(enc), valid


@_budget(150)
@given(csv_files())
def test_any_csv_record(file):
    raw, valid = file
    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / "d.csv"
        p.write_bytes(raw)
        try:
            d = cj.load_data(p)
        except cj.DataError as e:
            assert not valid, e
            assert "\n" not in str(e) and len(str(e)) < 600
        else:
            assert d.n >= MIN_SAMPLES and np.all(np.diff(d.ts) > 0)
            assert np.all(np.isfinite(d.ts)) and np.all(np.isfinite(d.phi))
        assert p.read_bytes() == raw


@_budget(8)
@given(csv_files().filter(lambda f: not f[1]))
def test_bad_csv_through_fit_exits_2_before_any_work(capsys, file):
    raw, _ = file
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        (d / "d.csv").write_bytes(raw)
        try:
            cj.load_data(d / "d.csv")
        except cj.DataError:
            pass
        else:
            return  # the spoiling happened to leave a valid record: nothing to test here
        code, err = _check_contract(["fit", d / "d.csv", "lab-rig", "--out", d / "r.json"],
                                    d, ["d.csv"], capsys)
        assert code == 2 and not (d / "r.json").exists()


# --- command lines ----------------------------------------------------------------------------

_HOSTILE = ["nan", "inf", "-inf", "1e400", "0", "-1", "", "abc", "1e-320", "9" * 400, "0x1"]
_PATHS = ["{d}/out.csv", "{d}/out.csv", "{d}", "{d}/no/such/x.csv", "{d}/s.toml", "",
          os.devnull, "{d}/with space é.csv"]


@st.composite
def simulate_argvs(draw):
    """A `simulate` command line: valid values, with none, one or a few hostile ones."""
    # Each valid (scene structure, samples, solver, extras) compiles once: CI keeps few.
    more = bool(_EXAMPLES)
    opts = {  # name: (valid values, hostile values)
        "scene": (["lab-rig", "{d}/s.toml"] + ["pendulum"] * more, ["nope", "{d}", "{d}/d.csv"]),
        "--t1": (["0.01", "0.02"], _HOSTILE), "--samples": (["3"] + ["5"] * more, _HOSTILE),
        "--phi0": (["0.3", "-2", "0"], _HOSTILE), "--dphi0": (["1", "-3"], _HOSTILE),
        "--rtol": (["1e-6", "1e-9"], _HOSTILE), "--atol": (["1e-9"], _HOSTILE),
        "--solver": (["auto"] + ["tsit5"] * more, ["rk4", "", "dopri8-uniform "]),
        "--extras": (["energy"] + ["energy,slider"] * more, ["junk", ",", "energy,,x"]),
        "--out": (["{d}/out.csv", os.devnull, "{d}/with space é.csv"], _PATHS),
        "--plot": (["{d}/p.png", "{d}/p.PDF"], ["{d}/p.xyz", "{d}/out.csv", "{d}", "{d}/p."]),
    }
    bad = set(draw(st.lists(st.sampled_from(sorted(opts)), max_size=3)))
    argv = ["simulate"]
    for name, (valid, hostile) in opts.items():
        if name in bad:
            value = draw(st.sampled_from(hostile))
        elif name in ("scene", "--out", "--t1", "--samples") or draw(st.booleans()):
            value = draw(st.sampled_from(valid))
        else:
            continue
        argv += [value] if name == "scene" else [name, value]
    return argv


@st.composite
def other_argvs(draw):
    """Commands whose valid runs are long: every line here has a mistake to catch first."""
    bad = draw(st.sampled_from([
        ["fit", "{d}/d.csv", "lab-rig", "--plot", "{d}/p.xyz"],
        ["fit", "{d}/d.csv", "{d}/s.toml", "--out", "{d}/s.toml"],
        ["fit", "{d}/d.csv", "lab-rig", "--multistart", "0"],
        ["fit", "{d}/d.csv", "lab-rig", "--sigma", "nan"],
        ["fit", "{d}/d.csv", "lab-rig", "--sigma", "1e300"],
        ["fit", "{d}/d.csv", "lab-rig", "--max-steps", "2147483648"],
        ["fit", "{d}/d.csv", "lab-rig", "--free", ","],
        ["fit", "{d}/d.csv"],
        ["demo", "--plot", "{d}/p.xyz"],
        ["demo", "--out", "{d}/no/r.json"],
        ["sweep", "lab-rig", "--n", "0", "--out", "{d}/x.npz"],
        ["sweep", "lab-rig", "--n", "10", "--out", "{d}/x.csv"],
        ["sweep", "lab-rig", "--n", "10", "--out", "{d}/x.npz", "--vary", "zz=1"],
        ["sweep", "lab-rig", "--n", "10", "--out", "{d}/x.npz", "--vary", "k=normal(1,"],
        ["synth", "{d}/s.toml", "--out", "{d}/s.toml"],
        ["synth", "lab-rig", "--rate", "1e300", "--out", "{d}/y.csv"],
        ["linearize", "{d}/nope.toml"],
        ["scenes", "--bogus"],
    ]))
    extra = draw(st.sampled_from([[], [], ["--seed", "-1"], ["--seed", "1e400"], ["--"]]))
    return bad + extra


@_budget(25)
@given(st.one_of(simulate_argvs(), simulate_argvs(), other_argvs()),
       st.booleans())
def test_any_command_line(capsys, argv, existing_out):
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        cj.save_scene(cj.load_scene("lab-rig"), d / "s.toml")
        cj.save_data(cj.synthesize(cj.load_scene("lab-rig"), t1=0.05, rate=100.0), d / "d.csv")
        if existing_out:
            (d / "out.csv").write_text("old\n")
        argv = [a.replace("{d}", tmp) for a in argv]
        positional = argv[1:next((i for i, a in enumerate(argv) if a.startswith("--")),
                                 len(argv))]
        inputs = [n for n in ("s.toml", "d.csv") if str(d / n) in positional]
        code, err = _check_contract(argv, d, inputs, capsys)
        if argv[0] != "simulate":
            assert code == 2, err
        assert code in (0, 2), err


# --- damaged program store (issue 24 defect 1) ------------------------------------------------

@st.composite
def store_damages(draw):
    """A damage to a stored program's bytes: a flipped byte at any position (header,
    output count, executable, digest), a truncation to any length, or any bytes appended."""
    kind = draw(st.sampled_from(["flip", "truncate", "append"]))
    if kind == "flip":
        i, x = draw(st.integers(0, 10**9)), draw(st.integers(1, 255))
        return f"flip {i} ^ {x}", lambda b: b[:i % len(b)] + bytes([b[i % len(b)] ^ x]) \
            + b[i % len(b) + 1:]
    if kind == "truncate":
        n = draw(st.integers(0, 10**9))
        return f"truncate {n}", lambda b: b[:n % len(b)]
    extra = draw(st.binary(min_size=1, max_size=64))
    return f"append {extra!r}", lambda b: b + extra


def _store_program():
    from crank_jax.runtime.persistent import PersistentProgram

    class Counted(PersistentProgram):
        compiled = 0

        def _compile(self, *a):
            self.compiled += 1
            return super()._compile(*a)

    return Counted(lambda x, w: (jnp.sin(x) * w, jnp.cumsum(x), jnp.sum(x)), "prop_store")


@_budget(8)
@given(store_damages())
def test_any_damaged_stored_program_is_recompiled_to_the_clean_result(damage):
    """A stored program damaged anywhere is a miss before it is deserialised: the call
    compiles again, returns the clean result, and stores an intact file in its place."""
    from crank_jax.runtime import persistent, program_store

    name, hurt = damage
    event(name.split()[0])
    x, w = jnp.linspace(0.0, 1.0, 5), jnp.asarray(2.0)
    with tempfile.TemporaryDirectory() as d, pytest.MonkeyPatch.context() as mp:
        store = Path(d)
        mp.setattr(persistent, "program_store_dir", lambda: store)
        clean = _store_program()(x, w)
        (path,) = store.glob("*.xla")
        blob = path.read_bytes()
        key = blob[len(program_store.MAGIC):len(program_store.MAGIC) + 64].decode()
        damaged = hurt(blob)
        path.write_bytes(damaged)
        prog = _store_program()
        out = prog(x, w)
        assert prog.compiled == 1, name
        for a, b in zip(out, clean, strict=True):
            np.testing.assert_array_equal(a, b)
        program_store.unpack(path.read_bytes(), key)  # replaced by an intact file


# --- fits on generated requests (issue 24.3, 24.8) ---------------------------------------------

_ZERO_START = ("T_c", "c_s", "F_s")  # >= 0 and 0 in the lab rig: fitted from 0


@_budget(2)
@given(st.lists(st.sampled_from(_ZERO_START), min_size=1, max_size=2, unique=True))
def test_sign_constrained_parameters_starting_at_zero_stay_valid(free):
    # A parameter that must be >= 0 and starts at 0: the fit never steps it below 0,
    # never raises, and its interval (when given) is cut at 0.
    scene = cj.load_scene("lab-rig")
    data = cj.synthesize(scene, t1=1.5, rate=100.0, noise_std=1e-3, seed=1)
    res = cj.fit(scene, data, free=("k", *free, "phi0", "dphi0"), progress=False, warn=False)
    for n in free:
        assert res.values[n] >= 0.0 and float(getattr(res.mech, n)) >= 0.0
        assert res.ci95[n] is None or res.ci95[n][0] >= 0.0
    assert all(math.isfinite(v) for v in res.values.values())


@st.composite
def degenerate_records(draw):
    """Records with no motion above their noise: a constant at any level, or Gaussian
    noise of any scale about any level (a pure-noise column, a crank at rest)."""
    n = draw(st.integers(20, 400))
    ts = np.arange(n) / draw(st.sampled_from([10.0, 200.0, 1e4]))
    level = draw(st.floats(-100.0, 100.0))
    scale = draw(st.sampled_from([0.0, 1e-9, 1e-3, 0.3, 10.0]))
    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    return cj.Data(ts, level + scale * rng.normal(size=n), source="degenerate.csv")


@_budget(6)
@given(degenerate_records())
def test_degenerate_records_are_refused_before_any_solve(data):
    res = cj.fit(cj.load_scene("lab-rig"), data, progress=False, warn=False)
    assert not res.converged and res.iterations == 0, res.message
    assert "no motion above its noise" in res.message
    assert all(math.isfinite(v) for v in res.values.values())


def test_budget_is_documented():
    assert "CRANK_JAX_PROPERTY_EXAMPLES" in (__doc__ or "")


# --- issue 24: hostile input classes ----------------------------------------------------------

_ANY_TEXT = st.text(st.characters(codec="utf-8"), max_size=40) | st.text(
    st.sampled_from('\x00\x07\x08\t\n\x0b\x0c\r\x1b\x7f\x85\u2028"\'\\ #=[]{}ué\ufeff'),
    max_size=12)


@_budget(40)
@given(_ANY_TEXT)
def test_any_description_round_trips(text):
    """Every string a scene can hold (any Unicode text: control characters, quotes,
    backslashes, newlines, TOML syntax) is written by save_scene and read back equal."""
    import dataclasses

    sc = dataclasses.replace(cj.load_scene("lab-rig"), description=text)
    with tempfile.TemporaryDirectory() as tmp:
        cj.save_scene(sc, Path(tmp) / "s.toml")
        again = cj.load_scene(Path(tmp) / "s.toml")
    assert again.description == text



@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this platform")
@_budget(10)
@given(st.sampled_from(["fit DATA", "fit --more-data", "fit SCENE", "validate DATA",
                        "validate SCENE", "simulate SCENE", "synth SCENE", "sweep SCENE"]),
       st.sampled_from(["fifo", "dir", "chardev", "missing"]))
def test_non_regular_inputs_exit_2_at_once(capsys, slot, kind):
    """Every input path (record, extra record, scene) that is a FIFO (no writer: opening
    it would wait forever), a directory, a device or missing exits 2 at once."""
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        cj.save_data(cj.synthesize(cj.load_scene("lab-rig"), t1=0.05, rate=100.0), d / "d.csv")
        bad = {"fifo": d / "p", "dir": d, "chardev": Path(os.devnull), "missing": d / "no"}[kind]
        if kind == "fifo":
            os.mkfifo(bad)
        command, where = slot.split()
        data, scene = (bad if where == "DATA" else d / "d.csv"), (
            bad if where == "SCENE" else "lab-rig")
        argv = {"fit": ["fit", data, scene, "--out", d / "r.json"]
                + (["--more-data", bad] if where == "--more-data" else []),
                "validate": ["validate", scene, data, "--out", d / "r.json"],
                "simulate": ["simulate", scene, "--out", d / "o.csv"],
                "synth": ["synth", scene, "--out", d / "o.csv"],
                "sweep": ["sweep", scene, "--n", "2", "--out", d / "x.npz"]}[command]
        code, err = _check_contract(argv, d, ["d.csv"], capsys)
        assert code == 2, err



_MAGNITUDE = st.sampled_from([0.0, 1e-300, 1e-12, 1e-9, 1e-3, 1.0, 1e8, 1.7e9, 1e100, 1e308])


@_budget(60)
@given(_MAGNITUDE, st.booleans(), st.lists(_MAGNITUDE.filter(lambda x: x > 0), min_size=4,
                                           max_size=8), st.booleans())
def test_any_time_scale(t0, negative, steps, through_file):
    """Records at any time offset and spacing (1e-300 s apart, +-1.7e308 s wide, Unix
    times): either accepted, with a span and spacings a solver can resolve, or refused in
    one line naming the row, never with a numpy warning (they are errors here)."""
    from crank_jax.records.data import MAX_TIME_SPAN, MIN_STEP_ULPS, MIN_TIME_STEP

    with np.errstate(over="ignore"):
        ts = (-t0 if negative else t0) + np.concatenate([[0.0], np.cumsum(steps)])
    phi = np.linspace(0.0, 1.0, ts.size)
    with tempfile.TemporaryDirectory() as tmp:
        try:
            if through_file:
                p = Path(tmp) / "d.csv"
                p.write_text("t,phi\n" + "".join(f"{t!r},{x!r}\n" for t, x in zip(ts, phi)))
                d = cj.load_data(p)
            else:
                d = cj.Data(ts, phi)
        except cj.DataError as e:
            assert "\n" not in str(e) and ("line " in str(e) or "sample " in str(e)), e
            event("refused")
        else:
            event("accepted")
            with np.errstate(over="ignore"):
                assert d.ts[-1] - d.ts[0] <= MAX_TIME_SPAN
            # (1 - 1e-9): the check's allowance for a 1 GHz grid computed in float64
            assert np.min(np.diff(d.ts)) >= MIN_TIME_STEP * (1 - 1e-9)
            scale = max(abs(d.ts[0]), abs(d.ts[-1]))
            assert np.min(np.diff(d.ts)) >= MIN_STEP_ULPS * np.spacing(scale)



_HUGE = ["1e308", "-1e308", "1e300", "1e30", "-1", "-5", "0.999999", "1e-300", "1e9", "1e8",
         "9223372036854775808", "-0.0"]


@_budget(20)
@given(st.lists(st.tuples(st.sampled_from(["--transient", "--noise-std", "--drop", "--rate",
                                           "--t-start", "--seed", "--jitter-std",
                                           "--transient-time", "--quantization", "--t1"]),
                          st.sampled_from(_HUGE)), min_size=1, max_size=2,
                unique_by=lambda x: x[0]))
def test_huge_synth_options_are_named(capsys, opts):
    """`synth` with huge, tiny or negative option values either writes a valid record or
    exits 2 with one line naming one of the options given (never "sample 0", a shape, or
    numpy's wording)."""
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        argv = ["synth", "lab-rig", "--out", d / "o.csv"]
        if "--t1" not in dict(opts):
            argv += ["--t1", "0.05"]
        for name, value in opts:
            argv += [name, value]
        code, err = _check_contract(argv, d, [], capsys)
        if code == 2:
            assert any(name in err for name, _ in opts), err
            assert "sample 0" not in err and "shape" not in err, err
        else:
            assert code == 0, err
            cj.load_data(d / "o.csv")



@_budget(8)
@given(st.sampled_from(["lab-rig", "near-buckling"]), st.floats(-12, -2))
def test_any_allowed_rtol_passes(capsys, preset, log_rtol):
    """Every --rtol that simulate accepts (up to 1e-2) finishes where the scene's own
    1e-8 does: a looser tolerance never fails where a tighter one passes."""
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        argv = ["simulate", preset, "--rtol", repr(10.0**log_rtol), "--quiet",
                "--out", d / "o.csv"]
        code, err = _check_contract(argv, d, [], capsys)
        assert code == 0, err



@_budget(20)
@given(st.floats(-1e6, 1e6, allow_subnormal=False), st.integers(0, 8), st.integers(20, 300),
       st.integers(0, 2**32 - 1))
def test_degenerate_records_are_refused_by_validate(value, ulps, n, seed):
    """A record whose scored angles are constant up to a few float64 spacings (what reading
    or converting a constant leaves) is refused by validate before any fit, in one line,
    instead of a fit_percent divided by rounding noise."""
    rng = np.random.default_rng(seed)
    phi = value + rng.integers(-ulps, ulps + 1, n) * np.spacing(value)
    data = cj.Data(np.arange(n) * 0.05, phi)
    with pytest.raises(cj.DataError, match="constant angle") as e:
        cj.validate(cj.load_scene("lab-rig"), data)
    assert "\n" not in str(e.value)



@_budget(15)
@given(st.sampled_from([(["--multistart", "0"], "--multistart"), (["--free", "zz"], "--free"),
                        (["--free", "k,tau1"], "--free"), (["--profile", "zz"], "--profile"),
                        (["--segments", "0"], "--segments"), (["--sigma", "inf"], "--sigma"),
                        (["--max-steps", "-3"], "--max-steps"), (["--seed", "-1"], "--seed"),
                        (["--plot", "{d}/p.xyz"], "--plot"),
                        (["--t-start", "2", "--t-end", "1"], "--t-start")]),
       csv_files().filter(lambda f: not f[1]), st.booleans())
def test_fit_option_mistakes_are_named_before_the_record(capsys, mistake, file, more):
    """A fit option mistake is reported, naming the option, whatever is wrong with the
    record too: every option is checked before any record is read."""
    (options, named), (raw, _) = mistake, file
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        (d / "d.csv").write_bytes(raw)
        argv = ["fit", d / "d.csv", "lab-rig"] + [o.replace("{d}", tmp) for o in options]
        if more:
            argv += ["--more-data", d / "d.csv"]
        code, err = _check_contract(argv, d, ["d.csv"], capsys)
        assert code == 2 and named in err, err


pytestmark = pytest.mark.filterwarnings("ignore::hypothesis.errors.NonInteractiveExampleWarning")
