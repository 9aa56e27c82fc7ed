"""A library that speaks its own language: its messages name the argument (`warmup=`,
`horizon=`, `freq_hz=`, `free=`) and the fix in API terms, never a command-line option;
the CLI prints the same message with the argument replaced by its option, from the one
table of `crank_jax.cli.wording`. Every case here is refused before any solve."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import equinox as eqx
import numpy as np
import pytest

import crank_jax as cj
from crank_jax.cli import main
from crank_jax.cli.wording import FLAGS, cli_message

SRC = Path(cj.__file__).parent
#: A command-line option: two dashes and a letter (not `--` alone, not a negative number;
#: not XLA's own `--xla_...` flags, which the runtime sets).
OPTION = re.compile(r"--(?!xla_)[a-z]")


# --- the table and the rewrite ----------------------------------------------------------

def test_cli_message_replaces_each_marked_argument_by_its_option():
    msg = ("`draws=` 10 x `chains=` 4 need 9 GiB; give `draws=` <= 3 (or fewer `chains=` "
           "or `warmup=` steps)")
    assert cli_message(msg) == ("--draws 10 x --chains 4 need 9 GiB; give --draws <= 3 (or "
                                "fewer --chains or --warmup steps)")
    # A value goes with its option, unquoted; an argument with no option stays as written.
    assert cli_message("`load_by='angle'` needs a turning crank, or `load_by='time'`") == (
        "--load-by angle needs a turning crank, or --load-by time")
    assert cli_message("`transient_hz=` -1 is bad") == "`transient_hz=` -1 is bad"
    # Only the marker is rewritten: a bare word or `name` without `=` is prose.
    assert cli_message("free parameters (`free`) and draws = 3") == (
        "free parameters (`free`) and draws = 3")
    assert cli_message("`freq_hz=`") == "--freq" and cli_message("`samples=`") == "--vary"


def test_every_option_in_the_table_is_one_the_cli_has():
    from crank_jax.cli.main import build_parser

    parser = build_parser()
    have = set()
    for action in parser._subparsers._group_actions:
        for sub in action.choices.values():
            for a in sub._actions:
                have.update(s for s in a.option_strings if s.startswith("--"))
    for arg, flag in FLAGS.items():
        assert set(flag.split("/")) <= have, (arg, flag)


# --- the same bad input: the API's words and the command's ------------------------------

def _api_words(e: BaseException, arg: str) -> str:
    text = str(e)
    assert f"`{arg}=`" in text, text
    assert not OPTION.search(text), text
    return text


def _cli_words(capsys, argv, flag: str, arg: str) -> str:
    capsys.readouterr()
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("crank-jax: error: "), err
    assert flag in err, err
    assert f"{arg}=" not in err and "`" not in err, err
    return err


@pytest.fixture(scope="module")
def record(tmp_path_factory) -> Path:
    """A 2 s lab-rig-like record at 100 Hz (its values do not matter: every case below is
    refused before a fit)."""
    path = tmp_path_factory.mktemp("rec") / "rec.csv"
    ts = np.arange(0.0, 2.0, 0.01)
    path.write_text("t,phi\n" + "".join(f"{float(t)!r},{0.3 * float(np.cos(8 * t))!r}\n"
                                       for t in ts))
    return path


def test_posterior_memory_refusal(tmp_path, capsys, record):
    from crank_jax.bayes.posterior import check_posterior_memory, posterior_bytes

    with pytest.raises(ValueError) as e:
        check_posterior_memory(10**9, 4, 500, 4, max_memory=posterior_bytes(10, 4, 500, 4))
    assert "give `draws=` <= 10 " in _api_words(e.value, "draws")
    with pytest.raises(ValueError) as e:
        check_posterior_memory(10, 4, 10**10, 4, max_memory=posterior_bytes(10, 4, 500, 4))
    assert "give `warmup=` <= " in _api_words(e.value, "warmup")
    err = _cli_words(capsys, ["posterior", record, "lab-rig", "--warmup", "10000000000",
                              "--out", tmp_path / "p.json"], "--warmup", "warmup")
    assert "give --warmup <= " in err and "--chains 4" in err


def test_horizon_refusal(tmp_path, capsys, record):
    data = cj.load_data(record)
    with pytest.raises(ValueError) as e:
        cj.validate(cj.load_scene("lab-rig"), data, horizon=1e-15, progress=False)
    assert "give `horizon=` at least" in _api_words(e.value, "horizon")
    err = _cli_words(capsys, ["validate", "lab-rig", record, "--horizon", "1e-15", "--out",
                              tmp_path / "v.json", "--quiet"], "--horizon", "horizon")
    assert "give --horizon at least" in err
    assert not (tmp_path / "v.json").exists()


def test_init_window_refusal(tmp_path, capsys, record):
    data = cj.load_data(record)
    with pytest.raises(ValueError) as e:
        cj.validate(cj.load_scene("lab-rig"), data, init_window=100.0, progress=False)
    assert "change the window or `init_window=`" in _api_words(e.value, "init_window")
    err = _cli_words(capsys, ["validate", "lab-rig", record, "--init-window", "100", "--out",
                              tmp_path / "v.json", "--quiet"], "--init-window", "init_window")
    assert "--init-window 100 s takes 200 of the window's 200 samples" in err


def test_fit_free_refusal(tmp_path, capsys, record):
    data = cj.load_data(record)
    with pytest.raises(ValueError) as e:
        cj.fit(cj.load_scene("lab-rig"), data, free=("k", "wat"), progress=False)
    assert "names unknown parameter(s) ['wat']" in _api_words(e.value, "free")
    _cli_words(capsys, ["fit", record, "lab-rig", "--free", "k,wat", "--out",
                        tmp_path / "f.json"], "--free", "free")


def test_per_record_refusal(tmp_path, capsys, record):
    data = cj.load_data(record)
    with pytest.raises(ValueError) as e:
        cj.fit(cj.load_scene("lab-rig"), [data, data], free=("k", "phi0", "dphi0"),
               per_record=("c",), progress=False)
    assert "free it (`free=`) or leave it out of `per_record=`" in _api_words(e.value,
                                                                               "per_record")


def test_vibration_start_frequency_refusal(tmp_path, capsys, monkeypatch):
    """No orbit at the range's start (the corrector is made to fail, so that nothing is
    compiled): the fix names the frequency range as each caller gave it."""
    import crank_jax.vibration.response as response

    def fails(scene, side, structure, f_ref, u_pred, t, rtol):
        n = np.asarray(u_pred).shape[0]
        return u_pred, np.eye(n - 1, n), False, 0, (0.0, 0.0, np.zeros(2))

    monkeypatch.setattr(response, "_correct", fails)
    sc = cj.load_scene("lab-rig")
    driven = eqx.tree_at(lambda s: s.torque, sc, cj.HarmonicLoad(0.0, 0.05, 4.0))
    with pytest.raises(ValueError) as e:
        cj.forced_response(driven, (3.0, 5.5))
    assert "a lower f0 in `freq_hz=`" in _api_words(e.value, "freq_hz")
    scene = tmp_path / "driven.toml"
    cj.save_scene(driven, scene)
    err = _cli_words(capsys, ["response", scene, "--freq", "3:5.5", "--out",
                              tmp_path / "r.json"], "--freq", "freq_hz")
    assert "a lower f0 in --freq" in err


def test_synthesize_refusal(tmp_path, capsys):
    with pytest.raises(ValueError) as e:
        cj.synthesize(cj.load_scene("lab-rig"), drop=0.999999)
    assert "lower `drop=` or sample more (`rate=`, `t1=`)" in _api_words(e.value, "drop")
    err = _cli_words(capsys, ["synth", "lab-rig", "--drop", "0.999999", "--out",
                              tmp_path / "d.csv"], "--drop", "drop")
    assert "lower --drop or sample more (--rate, --t1)" in err


# --- no library message names an option -------------------------------------------------

def _docstrings(tree: ast.AST) -> set[int]:
    out = set()
    for node in ast.walk(tree):
        if (isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
                and node.body and isinstance(node.body[0], ast.Expr)
                and isinstance(node.body[0].value, ast.Constant)):
            out.add(id(node.body[0].value))
    return out


def _option_strings(root: Path) -> list[str]:
    """Every string literal (an f-string's literal parts included) outside `cli/` and the
    docstrings that names a command-line option, unless it names the `crank-jax` command
    itself (a note addressed to the command's user, such as a fitted scene's comment)."""
    bad = []
    for path in sorted(root.rglob("*.py")):
        if "cli" in path.relative_to(root).parts:
            continue
        tree = ast.parse(path.read_text(), str(path))
        docs = _docstrings(tree)
        for node in ast.walk(tree):
            if (isinstance(node, ast.Constant) and isinstance(node.value, str)
                    and id(node) not in docs and OPTION.search(node.value)
                    and "crank-jax " not in node.value):
                bad.append(f"{path.relative_to(root)}:{node.lineno}: {node.value!r}")
    return bad


def test_no_library_message_names_a_command_line_option():
    assert _option_strings(SRC) == []


def test_the_scan_finds_an_option_in_a_message(tmp_path):
    (tmp_path / "cli").mkdir()
    (tmp_path / "cli" / "ok.py").write_text('raise ValueError("give --out")\n')
    (tmp_path / "mod.py").write_text(
        '"""Docstrings may say --warmup."""\n'
        'import warnings\n'
        'XLA = "--xla_cpu_flag="\n'
        'def f(x, option="--out"):\n'
        '    """`--horizon` for a reader."""\n'
        '    if x:\n'
        '        raise ValueError(f"x = {x} (--horizon) is bad")\n'
        '    warnings.warn("try a longer --warmup")\n'
        '    return "see `crank-jax validate --allow-unconverged`"\n')
    bad = sorted(_option_strings(tmp_path))
    assert [b.split(":")[:2] for b in bad] == [["mod.py", "4"], ["mod.py", "7"],
                                               ["mod.py", "8"]], bad
