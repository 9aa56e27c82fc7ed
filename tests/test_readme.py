"""The README's quick start runs as written (in a fresh interpreter, as a user pastes it)
and stays within its 15 lines."""

import os
import re
import subprocess
import sys
from pathlib import Path

README = Path(__file__).resolve().parent.parent / "README.md"


def _quick_start() -> str:
    text = README.read_text()
    section = text[text.index("## Quick start"):text.index("## Architecture")]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_quick_start_runs_and_is_short():
    code = _quick_start()
    assert len(code.strip().splitlines()) <= 15
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env["CRANK_JAX_NO_CACHE"] = "1"
    env.pop("JAX_NUM_CPU_DEVICES", None)
    p = subprocess.run([sys.executable, "-c", code + "\nimport os\nprint('XLA_FLAGS=' + "
                        "os.environ['XLA_FLAGS'], 'devices=' + str(jax.device_count()))\n"],
                       capture_output=True, text=True, env=env, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    # The fit's summary: k near its true value of 2 (the lab rig's), and converged.
    k = re.search(r"^k\s+\S+\s+(\S+)", p.stdout, re.M)
    assert k and abs(float(k.group(1)) - 2.0) < 1e-3, p.stdout[-2000:]
    assert "converged after" in p.stdout
    assert "xla_cpu_small_while_loop_byte_threshold" in p.stdout
    assert f"devices={len(os.sched_getaffinity(0))}" in p.stdout


def test_scene_format_example_loads_as_written(tmp_path):
    # The README's scene-format block is a complete scene: it loads, and its keys mean
    # what the comments say (a harmonic crank torque; an unknown key would be refused).
    import crank_jax as cj

    text = README.read_text()
    section = text[text.index("## Scene format"):text.index("## Headline numbers")]
    (tmp_path / "s.toml").write_text(re.search(r"```toml\n(.*?)```", section, re.S).group(1))
    scene = cj.load_scene(tmp_path / "s.toml")
    assert float(scene.torque.X1) == 0.05 and float(scene.torque.freq_hz) == 3.0
    assert float(scene.mech.k) == 2.0 and float(scene.phi0) == 1.0
