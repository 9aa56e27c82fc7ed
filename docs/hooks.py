"""mkdocs hook: the tutorials are scripts under docs/tutorials/, shown in their pages and,
when the environment variable CRANK_JAX_DOCS_RUN is set to 1, executed at build time with
their output shown under them (a script that fails fails the build). Without it the build
stays quick (CI's strict build) and the page says its output was not produced.

A page asks for a script with a line `<!-- tutorial: NAME.py -->`.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from mkdocs.exceptions import PluginError
from mkdocs.plugins import event_priority

ENV = "CRANK_JAX_DOCS_RUN"
TUTORIALS = Path(__file__).resolve().parent / "tutorials"
ROOT = TUTORIALS.parent.parent
MARKER = re.compile(r"^<!-- tutorial: ([\w.-]+\.py) -->$", re.M)
TIMEOUT_S = 900


def _run(script: Path) -> tuple[str, float]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT / "src"),
                                                      env.get("PYTHONPATH")]))
    env["MPLBACKEND"] = "Agg"
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as cwd:  # scripts write their files here
        p = subprocess.run([sys.executable, str(script)], cwd=cwd, env=env, text=True,
                           capture_output=True, timeout=TIMEOUT_S)
    if p.returncode != 0:
        raise PluginError(f"tutorial {script.name} failed (exit {p.returncode}):\n"
                          f"{p.stderr[-3000:]}")
    return p.stdout, time.perf_counter() - t0


def _block(match: re.Match) -> str:
    script = TUTORIALS / match.group(1)
    if not script.is_file():
        raise PluginError(f"tutorial script {script} does not exist")
    code = script.read_text().rstrip()
    out = [f'```python title="{script.name}"', code, "```", ""]
    if os.environ.get(ENV, "") == "1":
        text, seconds = _run(script)
        out += [f"Its output (run when these pages were built, {seconds:.0f} s):", "",
                "```text", text.rstrip() or "(no output)", "```"]
    else:
        out += ['!!! note "Output not shown"',
                f"    This build did not run the tutorials; `{ENV}=1 mkdocs build` runs "
                f"each and shows its output. Or run it yourself: `python {script.name}`."]
    return "\n".join(out)


def on_page_markdown(markdown: str, page, config, files) -> str:
    return MARKER.sub(_block, markdown)


@event_priority(0)  # before autorefs resolves the references (its on_env runs at -50)
def on_env(env, config, files):
    """Let a docstring's `[name][]` find `name` wherever it is documented: register each
    rendered object's last name as an identifier of its own, when that name is unique (an
    ambiguous one still fails the strict build)."""
    autorefs = config.plugins.get("autorefs")
    urls = getattr(autorefs, "_secondary_url_map", None)
    primary = getattr(autorefs, "_primary_url_map", None)
    if urls is None or primary is None:
        return env
    by_short: dict[str, set[str]] = {}
    for identifier in primary:
        if identifier.startswith("crank_jax."):
            by_short.setdefault(identifier.rsplit(".", 1)[1], set()).add(identifier)
    for short, ids in by_short.items():
        # The least nested wins (a module's function over a class's method of that name).
        depth = min(i.count(".") for i in ids)
        best = [i for i in ids if i.count(".") == depth]
        if len(best) == 1 and short not in primary and short not in urls:
            urls[short] = list(primary[best[0]])
    return env
