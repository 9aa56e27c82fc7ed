"""The documentation site (mkdocs.yml) builds in strict mode, so a broken link, a
cross-reference a docstring cannot resolve or a page missing from the nav fails CI; and
(slow) its tutorials run and their output is on their pages."""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TUTORIALS = ROOT / "docs" / "tutorials"


def _build(site: Path, run_tutorials: bool, timeout: int) -> float:
    for module in ("mkdocs", "material", "mkdocstrings_handlers.python"):
        if importlib.util.find_spec(module.split(".")[0]) is None:
            pytest.skip(f"{module} is not installed: pip install -e '.[docs]'")
    env = {k: v for k, v in os.environ.items() if k != "CRANK_JAX_DOCS_RUN"}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT / "src"),
                                                      env.get("PYTHONPATH")]))
    env["NO_MKDOCS_2_WARNING"] = "1"
    if run_tutorials:
        env["CRANK_JAX_DOCS_RUN"] = "1"
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f",
                        str(ROOT / "mkdocs.yml"), "-d", str(site)], cwd=ROOT, env=env,
                       capture_output=True, text=True, timeout=timeout)
    assert p.returncode == 0, p.stderr[-4000:]
    return time.perf_counter() - t0


def _page(site: Path, name: str) -> str:
    return (site / name / "index.html").read_text()


def test_docs_build_strict(tmp_path):
    site = tmp_path / "site"
    seconds = _build(site, run_tutorials=False, timeout=600)
    print(f"mkdocs build --strict: {seconds:.1f} s")
    # The API reference is generated from the docstrings.
    ref = _page(site, "reference/identify")
    assert 'id="crank_jax.identify.fit.fit"' in ref and "Fit free parameters" in ref
    # Every tutorial script is on a page; unrun, the page says so.
    scripts = sorted(p.name for p in TUTORIALS.glob("*.py"))
    pages = "".join(_page(site, f"tutorials/{p.stem.replace('_', '-')}") for p in
                    sorted(TUTORIALS.glob("*.py")))
    assert scripts and all(s in pages for s in scripts)
    assert "Output not shown" in pages
    # The site makes no request to a font or script host.
    assert not re.search(r"""(src|href)=["']https?://fonts\.""", _page(site, ""))


@pytest.mark.slow
def test_tutorials_run(tmp_path):
    """CRANK_JAX_DOCS_RUN=1: every tutorial runs (a failure fails the build) and its
    output is on its page."""
    site = tmp_path / "site"
    _build(site, run_tutorials=True, timeout=1800)
    assert "converged after" in _page(site, "tutorials/free-decay")
    assert "fit 99." in _page(site, "tutorials/validation")
    assert "channel x_s: rms" in _page(site, "tutorials/rotating-rig")
    assert "rms angle error" in _page(site, "tutorials/user-term")
    assert "Output not shown" not in _page(site, "tutorials/sweep")
