"""Every concrete `crank-jax` command line in README.md and in the docs pages its command
line, sweep and identification sections moved to (`PAGES`) runs as written.

The lines are taken from those pages' fenced code blocks (continuations joined, comments
dropped; a `[--option ...]` group is run with its options; usage lines with placeholders
such as `SCENE`, `...` or `[the same fit options]` are skipped) and run in order, block by
block, in a fresh directory with the repository's scene files, each in a fresh interpreter
as a user would type it. The CLI asks for one CPU device per core (two on the CI machine);
the sweep also runs on four forced devices (`JAX_NUM_CPU_DEVICES=4`, more than there are
cores).
"""

import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
#: The pages read, in order: the README and the guide pages its CLI sections moved to.
PAGES = (README, *(ROOT / "docs" / p for p in (
    "guide/cli.md", "guide/sweeps.md", "guide/identification.md", "benchmarks/identification.md")))
#: The one sweep the issue found failing on several devices; quick, so never marked slow.
QUICK_SWEEP = ("crank-jax sweep lab-rig --vary 'k=normal(2,0.1)' --n 4 "
               "--outputs peak_phi,peak_O --out x.npz")
#: Commands that take minutes (a fit compiles its programs cold, the big sweep runs 10^5).
SLOW = ("demo", "fit", "validate", "posterior", "design")


def _blocks() -> list[list[str]]:
    """The runnable `crank-jax` lines of each fenced block, in order."""
    blocks = []
    text = "\n".join(p.read_text() for p in PAGES)
    for body in re.findall(r"^```[a-z]*\n(.*?)^```", text, re.S | re.M):
        body = body.replace("\\\n", " ")
        lines = []
        for line in body.splitlines():
            line = re.sub(r"\s+#.*$", "", line).strip()
            if not line.startswith("crank-jax ") or re.search(
                    r"\.\.\.|\||\b[A-Z]{2,}\b|\[[^-]", line):
                continue
            lines.append(" ".join(line.replace("[", " ").replace("]", " ").split()))
        if lines:
            blocks.append(lines)
    return blocks


def _env(**extra) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_NUM_CPU_DEVICES")}
    env.update(CRANK_JAX_NO_CACHE="1", JAX_PLATFORMS="cpu",
               PYTHONPATH=os.pathsep.join([str(ROOT / "src"), env.get("PYTHONPATH", "")]))
    env.update(extra)
    return env


def _workdir(tmp_path: Path) -> Path:
    # The README's paths are relative to the repository: its scene files, a figures folder.
    shutil.copytree(ROOT / "experiments" / "scenes", tmp_path / "experiments" / "scenes")
    (tmp_path / "docs" / "figures").mkdir(parents=True)
    return tmp_path


def _run(line: str, cwd: Path, env: dict) -> subprocess.CompletedProcess:
    argv = [sys.executable, "-m", "crank_jax", *shlex.split(line)[1:]]
    p = subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, f"{line}\nexit {p.returncode}: {p.stderr[-2000:]}"
    return p


def test_the_readme_has_the_documented_examples():
    lines = [ln for block in _blocks() for ln in block]
    for command in ("sweep", "simulate", "synth", "fit", "validate", "demo", "linearize"):
        assert any(ln.split()[1] == command for ln in lines), command
    assert QUICK_SWEEP in lines


@pytest.mark.parametrize("devices", [None, "4"])
def test_the_readme_sweep_runs_on_one_device_per_core_and_on_more(tmp_path, devices):
    env = _env() if devices is None else _env(JAX_NUM_CPU_DEVICES=devices)
    p = _run(QUICK_SWEEP, _workdir(tmp_path), env)
    want = "4 device(s)" if devices else f"{len(os.sched_getaffinity(0))} device(s)"
    assert "4 samples of peak_phi, peak_O (4 ok" in p.stderr and want in p.stderr, p.stderr
    assert (tmp_path / "x.npz").stat().st_size > 0


def test_the_quick_readme_commands_run(tmp_path):
    # Every block whose commands take seconds (simulate, linearize, the quick sweep).
    cwd = _workdir(tmp_path)
    for block in _blocks():
        if any(ln.split()[1] in SLOW for ln in block) or "100000" in " ".join(block):
            continue
        for line in block:
            if line != QUICK_SWEEP:  # run above, on several device counts
                _run(line, cwd, _env())


@pytest.mark.slow
def test_every_readme_command_runs(tmp_path):
    cwd = _workdir(tmp_path)
    for block in _blocks():
        for line in block:
            _run(line, cwd, _env())
