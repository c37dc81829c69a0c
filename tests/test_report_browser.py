"""``report.html`` in a real headless Chromium: every figure renders, and the console stays clean.

The page is written by ``ermrl report`` from a tiny real study and test phase (CartPole, a few
hundred steps per run), then moved alone to another folder before Chromium opens it, so what it
shows comes from the page itself. Chromium is driven from its command line, with no Python
browser package: ``--screenshot`` takes the screenshot, and ``--dump-dom`` prints the DOM of a
copy of the page into which a small script, run before the page's own content, writes what it
measured (each image's ``naturalWidth``, every error event and ``console.error`` call) as
attributes of ``<html>``. Chromium's own console log (``--enable-logging=stderr``) is checked as
well.

Chromium is Debian's ``chromium`` package (``scripts/install_system_deps.sh`` installs it). The
tests are skipped without it, unless ``ERMRL_REQUIRE_SERVICES=1`` (CI), where they fail.
"""

from __future__ import annotations

import contextlib
import html
import io
import json
import os
import re
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")

# Runs first (inserted right after <head>): records failed loads (they do not bubble, hence
# the capture phase), uncaught errors and console.error calls; after `load`, each image's
# naturalWidth. Results go to attributes of <html>, which --dump-dom prints.
PROBE = """<script>
(function () {
  var errors = [];
  var root = document.documentElement;
  function keep(text) { errors.push(String(text)); root.setAttribute('data-errors', JSON.stringify(errors)); }
  window.addEventListener('error', function (e) {
    var t = e.target;
    keep(t && t !== window && t.tagName ? 'failed to load <' + t.tagName.toLowerCase() + '>' : e.message);
  }, true);
  window.addEventListener('unhandledrejection', function (e) { keep('unhandled rejection: ' + e.reason); });
  var original = console.error;
  console.error = function () { keep(Array.prototype.join.call(arguments, ' ')); return original.apply(console, arguments); };
  root.setAttribute('data-errors', '[]');
  window.addEventListener('load', function () {
    var widths = Array.prototype.map.call(document.images, function (img) { return img.naturalWidth; });
    root.setAttribute('data-image-widths', JSON.stringify(widths));
  });
})();
</script>"""


def chromium() -> str:
    """The Chromium binary; skips (or fails, with ``ERMRL_REQUIRE_SERVICES=1``) without one."""
    for name in CHROMIUM_NAMES:
        found = shutil.which(name)
        if found:
            return found
    reason = (
        "no headless Chromium (Debian: apt-get install chromium, or bash "
        "scripts/install_system_deps.sh)"
    )
    if os.environ.get("ERMRL_REQUIRE_SERVICES") == "1":
        pytest.fail(reason)
    pytest.skip(reason)


def _chromium_run(binary: str, *args: str, home: Path) -> subprocess.CompletedProcess[str]:
    # --no-sandbox: CI containers run as root, where Chromium's sandbox cannot start.
    # A fresh profile folder each time, so no state from another run leaks in.
    return subprocess.run(
        [
            binary, "--headless", "--disable-gpu", "--no-sandbox", "--no-first-run",
            "--disable-dev-shm-usage", f"--user-data-dir={home}", "--enable-logging=stderr",
            "--v=0", "--virtual-time-budget=10000", *args,
        ],
        capture_output=True, text=True, timeout=180, env={**os.environ, "HOME": str(home)},
    )  # fmt: skip


@dataclass
class PageCheck:
    """What Chromium saw of a page."""

    image_widths: list[int]
    errors: list[str]  # error events and console.error calls, from the page
    console: list[str]  # Chromium's console log lines (stderr)


def open_in_chromium(page: Path, work: Path) -> PageCheck:
    """Load ``page`` (a copy with :data:`PROBE`) and read back what the probe recorded."""
    binary = chromium()
    text = page.read_text()
    probed = page.with_name(page.stem + ".probed.html")  # beside it: the same base URL
    head = re.search(r"<head[^>]*>", text, flags=re.IGNORECASE)
    at = head.end() if head else 0
    probed.write_text(text[:at] + PROBE + text[at:])
    try:
        proc = _chromium_run(binary, "--dump-dom", probed.resolve().as_uri(), home=work / "dom")
    finally:
        probed.unlink()
    assert proc.returncode == 0, proc.stderr[-2000:]
    root = re.search(r"<html[^>]*>", proc.stdout)
    assert root, proc.stdout[:500]

    def attribute(name: str) -> list:  # noqa: ANN401 (JSON)
        found = re.search(rf'{name}="([^"]*)"', root.group(0))
        assert found, f"the probe did not run: no {name} in {root.group(0)[:300]}"
        return json.loads(html.unescape(found.group(1)))

    console = [line for line in proc.stderr.splitlines() if ":CONSOLE" in line]
    return PageCheck(attribute("data-image-widths"), attribute("data-errors"), console)


def screenshot(page: Path, png: Path, work: Path) -> None:
    proc = _chromium_run(
        chromium(), f"--screenshot={png}", "--window-size=1280,2400", "--hide-scrollbars",
        page.resolve().as_uri(), home=work / "shot",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]


@pytest.fixture(scope="module")
def report_page(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``report.html`` of a tiny CartPole study and test phase, moved alone to a new folder."""
    chromium()  # skip before training anything
    from ermrl.analysis import write_report
    from ermrl.cli import evolve_main, test_main

    root = tmp_path_factory.mktemp("browser")
    storage, name = f"sqlite:///{root}/study.db", "cartpole-browser"
    common = ["--storage", storage, "--study-name", name, "--quiet"]
    with contextlib.redirect_stderr(io.StringIO()):
        assert evolve_main([
            "--env-id", "CartPole-v1", "--n-trials", "4", "--n-seeds", "1", "--training-steps",
            "256", "--units", "10", "--n-envs", "1", "--sampler-seed", "0",
            "--ppo", "n_steps=128", "batch_size=64", "n_epochs=1", *common,
        ]) == 0  # fmt: skip
        assert test_main([
            *common, "--agents", "ppo", "res-ppo", "--seeds", "10", "11",
            "--training-steps", "256", "--out", str(root / "runs"),
        ]) == 0  # fmt: skip
    result = write_report(name, storage, runs=root / "runs", out=root / "report")
    assert result.html is not None
    elsewhere = root / "elsewhere"
    elsewhere.mkdir()
    return Path(shutil.move(str(result.html), elsewhere / "report.html"))


def test_every_figure_of_the_report_renders_in_chromium(report_page: Path) -> None:
    n_img = report_page.read_text().count("<img ")
    assert n_img >= 5  # evolution, test phase and dynamics figures
    seen = open_in_chromium(report_page, report_page.parent)
    assert len(seen.image_widths) == n_img
    assert all(w > 0 for w in seen.image_widths), seen.image_widths
    assert seen.errors == [] and seen.console == [], (seen.errors, seen.console)


def test_the_report_screenshot_is_a_page_not_a_blank(report_page: Path, tmp_path: Path) -> None:
    import numpy as np
    from PIL import Image

    png = tmp_path / "report.png"
    screenshot(report_page, png, tmp_path)
    shot = np.asarray(Image.open(png).convert("L"), dtype=np.float64)
    assert shot.shape == (2400, 1280)
    # Text and figures: many grey levels, and not a white page.
    assert len(np.unique(shot)) > 50 and shot.std() > 10 and shot.mean() < 250


def test_the_probe_sees_a_broken_image_and_a_console_error(tmp_path: Path) -> None:
    """The checks above could not pass on a broken page: a bad image and a console error."""
    page = tmp_path / "broken.html"
    page.write_text(
        "<!DOCTYPE html><html><head><title>x</title></head><body>"
        '<img src="data:image/png;base64,AAAA"><img src="missing.png">'
        "<script>console.error('boom')</script></body></html>"
    )
    seen = open_in_chromium(page, tmp_path)
    assert seen.image_widths == [0, 0]
    assert "boom" in seen.errors and sum("failed to load <img>" in e for e in seen.errors) == 2
    assert any("boom" in line for line in seen.console), seen.console
