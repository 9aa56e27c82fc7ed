"""The HTML reports (`crank-jax fit/validate --report`, `FitResult.report`,
`Validation.report`): self-contained, no network request, the numbers of fit.json, and a
page with content when a real headless browser renders it."""

from __future__ import annotations

import base64
import contextlib
import fcntl
import hashlib
import html as html_lib
import json
import os
import re
import select
import shutil
import subprocess
import sys
import time
import tomllib
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

import crank_jax as cj
from crank_jax.cli import main
from crank_jax.scene import scene_from_dict

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A pendulum record, its fit through the CLI with --out and --report, and the
    validation of the fitted scene on a second record with --report."""
    d = tmp_path_factory.mktemp("report")
    rec, rec2 = d / "rec.csv", d / "rec2.csv"
    for path, seed in ((rec, "4"), (rec2, "5")):
        assert main(["synth", "pendulum", "--t1", "2", "--rate", "50", "--noise-std", "0.002",
                     "--seed", seed, "--out", str(path)]) == 0
    out, html, toml = d / "fit.json", d / "fit.html", d / "fitted.toml"
    assert main(["fit", str(rec), "pendulum", "--free", "c,phi0,dphi0", "--out", str(out),
                 "--report", str(html), "--scene-out", str(toml), "--quiet"]) == 0
    vout, vhtml = d / "val.json", d / "val.html"
    assert main(["validate", str(toml), str(rec2), "--init-window", "0.3", "--out",
                 str(vout), "--report", str(vhtml), "--quiet"]) == 0
    return dict(dir=d, rec=rec, rec2=rec2, json=out, html=html, vjson=vout, vhtml=vhtml,
                toml=toml)


class _Cells(HTMLParser):
    """Collects, per table row with a data-name, the text and title of its cells."""

    def __init__(self):
        super().__init__()
        self.rows: dict[str, list[tuple[str, str, str]]] = {}
        self._row: str | None = None
        self._cell: list | None = None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "tr":
            self._row = a.get("data-name")
            if self._row is not None:
                self.rows[self._row] = []
        elif tag == "td" and self._row is not None:
            self._cell = [a.get("data-key", ""), a.get("title", ""), ""]

    def handle_data(self, data):
        if self._cell is not None:
            self._cell[2] += data

    def handle_endtag(self, tag):
        if tag == "td" and self._cell is not None and self._row is not None:
            self.rows[self._row].append(tuple(c.strip() for c in self._cell))
            self._cell = None
        elif tag == "tr":
            self._row = None


def _rows(html: str) -> dict:
    p = _Cells()
    p.feed(html)
    return p.rows


def _check_fit_numbers(html: str, doc: dict) -> None:
    """Every estimate cell shows fit.json's value to 6 digits, with the exact value as
    its title."""
    rows = _rows(html)
    assert set(doc["estimates"]) <= set(rows)
    keys = {"start": lambda e: e["start"], "value": lambda e: e["value"],
            "stderr": lambda e: e["stderr"], "lo": lambda e: e["ci95"][0],
            "hi": lambda e: e["ci95"][1]}
    for name, e in doc["estimates"].items():
        cells = {k: (title, text) for k, title, text in rows[name] if k}
        assert set(cells) == set(keys)
        for key, get in keys.items():
            title, text = cells[key]
            want = get(e)
            assert float(title) == want, (name, key)
            assert float(text) == pytest.approx(want, rel=5e-6, abs=0), (name, key, text)


def test_fit_report_shows_fit_json(fitted):
    html, doc = fitted["html"].read_text(), json.loads(fitted["json"].read_text())
    _check_fit_numbers(html, doc)
    assert "N*m*s/rad" in html  # c's unit
    # Verdicts in words, the correlation heat map, both figures (inline SVG).
    assert "Identifiable: the data determine every free parameter" in html
    assert ("are white" in html) == doc["diagnostics"]["white"]
    assert html.count('<table class="heat"') == 1 and html.count("<svg") == 2
    r = doc["estimates"]["c"]["correlation"]["phi0"]
    assert f'title="{r!r}">{r:.2f}<' in html


def test_fit_report_provenance(fitted):
    html = fitted["html"].read_text()
    sha = hashlib.sha256(fitted["rec"].read_bytes()).hexdigest()
    assert sha in html and str(fitted["rec"]) in html
    assert "crank-jax fit " in html and "--report" in html
    for dist in ("jax", "diffrax", "crank-jax"):
        assert f"<th>{dist}</th>" in html
    # The scene as given and the fitted one, as TOML the loader reads back.
    given = re.search(r'<pre id="scene-toml">(.*?)</pre>', html, re.S).group(1)
    scene = scene_from_dict(tomllib.loads(html_lib.unescape(given)))
    assert scene.mech == cj.load_scene("pendulum").mech
    assert re.search(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\+00:00", html)


def test_report_has_no_remote_reference(fitted):
    for key in ("html", "vhtml"):
        html = fitted[key].read_text()
        assert "default-src 'none'" in html  # the browser refuses any fetch
        assert not re.search(r"""(src|href)\s*=\s*["']?\s*(https?:|//|ftp:)""", html, re.I)
        assert not re.search(r"url\(\s*['\"]?(https?:|//)", html, re.I)
        assert "<script" not in html and "<link" not in html


def test_validation_report_shows_val_json(fitted):
    html, doc = fitted["vhtml"].read_text(), json.loads(fitted["vjson"].read_text())
    rows = _rows(html)
    for name, key in (("fit", "fit_percent"), ("rms error", "rms"),
                      ("max |error|", "max_abs"), ("phi0 (estimated)", "phi0")):
        (_, title, text), = [c for c in rows[name] if c[1]]
        assert float(title) == doc[key] and float(text) == pytest.approx(doc[key], rel=5e-6)
    assert hashlib.sha256(fitted["rec2"].read_bytes()).hexdigest() in html
    assert "crank-jax validate " in html and html.count("<svg") == 2


def test_report_methods_write_atomically(fitted, tmp_path):
    """The library methods: FitResult.report and Validation.report."""
    scene = cj.load_scene("pendulum")
    data = cj.load_data(fitted["rec"])
    res = cj.fit(scene, data, free=("c",), progress=False, warn=False)
    path = tmp_path / "r.html"
    res.report(path, scene=scene, command="my-script.py")
    html = path.read_text()
    _check_fit_numbers(html, res.to_json())
    assert "my-script.py" in html and [p.name for p in tmp_path.iterdir()] == ["r.html"]
    val = cj.validate(cj.load_scene(fitted["toml"]), cj.load_data(fitted["rec2"]),
                      init_window=0.3)
    val.report(tmp_path / "v.html")
    assert f"{val.fit_percent:.6g}" in (tmp_path / "v.html").read_text()


def test_long_records_embed_png():
    """Above SVG_MAX_POINTS plotted points a figure is a base64 PNG (an SVG would grow to
    megabytes); below, inline SVG without the XML prolog."""
    from crank_jax.report.figures import SVG_MAX_POINTS, embed
    from crank_jax.report.plotting import pyplot

    def figure():
        fig, ax = pyplot().subplots()
        ax.plot(np.arange(10.0))
        return fig

    png = embed(figure(), SVG_MAX_POINTS + 1)
    assert png.startswith('<img alt="figure" src="data:image/png;base64,iVBOR')
    svg = embed(figure(), 10)
    assert svg.startswith("<svg") and "<!DOCTYPE" not in svg


def _one_error(argv, capsys) -> str:
    rc = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    return err[0]


def test_report_path_checked_before_work(fitted, tmp_path, capsys):
    rec = str(fitted["rec"])
    base = ["fit", rec, "pendulum", "--free", "c", "--quiet"]
    assert "--report" in _one_error(base + ["--report", str(tmp_path / "no" / "r.html")],
                                    capsys)
    assert "--report" in _one_error(base + ["--report", rec], capsys)
    same = str(tmp_path / "x")
    assert "is the same file as --out" in _one_error(base + ["--out", same, "--report", same],
                                                      capsys)
    vbase = ["validate", str(fitted["toml"]), str(fitted["rec2"]), "--out",
             str(tmp_path / "v.json"), "--quiet"]
    assert "--report" in _one_error(vbase + ["--report", str(fitted["rec2"])], capsys)
    assert "--report" in _one_error(vbase + ["--report", str(tmp_path / "no" / "v.html")],
                                    capsys)
    assert list(tmp_path.iterdir()) == []


# --- a real browser ---------------------------------------------------------------------

def _browser() -> str:
    for name in BROWSERS:
        if path := shutil.which(name):
            return path
    pytest.skip(f"no headless browser on PATH (looked for {', '.join(BROWSERS)}; on Debian: "
                "apt-get install chromium)")


def _above(fd: int, low: int = 10) -> int:
    """`fd` moved to a number >= `low` (clear of the 3 and 4 the browser's pipe needs)."""
    new = fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, low)
    os.close(fd)
    return new


class _Browser:
    """A headless browser driven over the DevTools protocol on a pipe (`--remote-debugging-
    pipe`: commands on its fd 3, replies and events on its fd 4, NUL-separated JSON), which
    records every network request the page itself makes (not the browser's own update and
    clock traffic)."""

    def __init__(self, profile: Path):
        cmd_r, self._cmd_w = (_above(fd) for fd in os.pipe())
        self._resp_r, resp_w = (_above(fd) for fd in os.pipe())
        # A small Python trampoline moves the pipe ends to the browser's fds 3 and 4 (no
        # preexec_fn: a fork beside JAX's threads is unsafe, and JAX warns of it).
        move = (f"import os, sys; os.dup2({cmd_r}, 3); os.dup2({resp_w}, 4); "
                "os.execv(sys.argv[1], sys.argv[1:])")
        self.proc = subprocess.Popen(
            [sys.executable, "-c", move, _browser(),
             "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
             "--no-first-run", f"--user-data-dir={profile}", "--remote-debugging-pipe",
             "about:blank"], pass_fds=(cmd_r, resp_w),
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        os.close(cmd_r)
        os.close(resp_w)
        self._buf, self._id, self.events = b"", 0, []

    def _message(self, deadline: float) -> dict:
        while b"\0" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self._resp_r], [], [], left)[0]:
                raise TimeoutError("the browser did not answer")
            chunk = os.read(self._resp_r, 1 << 20)
            if not chunk:
                raise EOFError("the browser closed its pipe")
            self._buf += chunk
        msg, self._buf = self._buf.split(b"\0", 1)
        return json.loads(msg)

    def call(self, method: str, session: str | None = None, **params) -> dict:
        self._id += 1
        msg = {"id": self._id, "method": method, "params": params}
        if session:
            msg["sessionId"] = session
        os.write(self._cmd_w, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + 60
        while True:
            m = self._message(deadline)
            if m.get("id") == self._id:
                assert "error" not in m, m
                return m["result"]
            self.events.append(m)

    def wait_for(self, method: str, seconds: float = 60) -> None:
        deadline = time.monotonic() + seconds
        while not any(e.get("method") == method for e in self.events):
            self.events.append(self._message(deadline))

    def open(self, page: Path) -> str:
        """Open `page` in a new tab, with network events on; wait for its load event."""
        target = self.call("Target.createTarget", url="about:blank")["targetId"]
        session = self.call("Target.attachToTarget", targetId=target,
                            flatten=True)["sessionId"]
        for domain in ("Network.enable", "Page.enable"):
            self.call(domain, session)
        self.call("Emulation.setDeviceMetricsOverride", session, width=1100, height=1400,
                  deviceScaleFactor=1, mobile=False)
        self.call("Page.navigate", session, url=page.as_uri())
        self.wait_for("Page.loadEventFired")
        return session

    def requests(self) -> list[str]:
        return [e["params"]["request"]["url"] for e in self.events
                if e.get("method") == "Network.requestWillBeSent"]

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.call("Browser.close")
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.proc.wait(timeout=20)
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        os.close(self._cmd_w)
        os.close(self._resp_r)


@contextlib.contextmanager
def _browser_session(profile: Path):
    b = _Browser(profile)
    try:
        yield b
    finally:
        b.close()


def test_browser_renders_report_offline(fitted, tmp_path):
    """Chromium renders the report: the page requests nothing but itself (while a control
    page with one remote image is seen requesting it), the DOM holds fit.json's numbers,
    and the screenshot has content."""
    _browser()
    control = tmp_path / "control.html"
    control.write_text('<html><body><img src="http://crank-jax.invalid/x.png"></body></html>')
    with _browser_session(tmp_path / "p0") as b:
        b.open(control)
    assert "http://crank-jax.invalid/x.png" in b.requests(), "the check is blind"
    with _browser_session(tmp_path / "p1") as b:
        session = b.open(fitted["html"])
        time.sleep(0.5)  # anything late would still be caught by the next call's events
        dom = b.call("Runtime.evaluate", session, expression="document.documentElement"
                     ".outerHTML", returnByValue=True)["result"]["value"]
        shot = b.call("Page.captureScreenshot", session, format="png",
                      captureBeyondViewport=True)["data"]
    assert b.requests() == [fitted["html"].as_uri()]
    _check_fit_numbers(dom, json.loads(fitted["json"].read_text()))
    path = tmp_path / "shot.png"
    path.write_bytes(base64.b64decode(shot))
    import matplotlib.image

    img = matplotlib.image.imread(path)[..., :3]
    ink = np.any(img < 0.9, axis=-1)  # pixels that are not (nearly) white
    assert img.shape[0] > 2000 and img.std() > 0.05 and 0.02 < ink.mean() < 0.8, (
        img.shape, img.std(), ink.mean())
