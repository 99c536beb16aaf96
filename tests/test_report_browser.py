"""Open the generated report in headless Chromium (issue 4 evidence).

Checks that the page loads without console messages or script errors, that
every figure and typeset equation decodes (the page's own on-load check sets
``<body data-figures-ok>``), that the figure count matches, and saves a
screenshot (copied to docs/report_screenshot.png when VSIDGEN_SAVE_SCREENSHOT=1).

Skipped when Chromium is absent, unless VSIDGEN_REQUIRE_BROWSER=1.
Install: ``apt-get install -y chromium`` (Debian).
"""

from __future__ import annotations

import os
import pathlib
import re
import shutil
import subprocess

import pytest

from report_fixture import OUTPUTS, STATES, write_results_dir
from vsidgen.report import write_report

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--hide-scrollbars", "--virtual-time-budget=5000"]


def _chromium() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        exe = shutil.which(name) or (f"/usr/bin/{name}" if os.path.exists(f"/usr/bin/{name}") else None)
        if exe:
            return exe
    msg = "headless Chromium not installed (apt-get install -y chromium)"
    if os.environ.get("VSIDGEN_REQUIRE_BROWSER") == "1":
        pytest.fail(msg + "; VSIDGEN_REQUIRE_BROWSER=1")
    pytest.skip(msg)


def _run(exe: str, tmp: pathlib.Path, tag: str, *args: str) -> subprocess.CompletedProcess:
    cmd = [exe, *FLAGS, f"--user-data-dir={tmp / ('profile-' + tag)}", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120)


def _load(exe: str, tmp: pathlib.Path, page: pathlib.Path, tag: str):
    """Dump the DOM after load; return (body attributes, console lines)."""
    proc = _run(exe, tmp, tag, "--enable-logging=stderr", "--v=0", "--dump-dom", page.as_uri())
    assert proc.returncode == 0, proc.stderr[-2000:]
    m = re.search(r"<body([^>]*)>", proc.stdout)
    assert m, "no <body> in DOM dump:\n" + proc.stdout[:500]
    attrs = dict(re.findall(r'([\w-]+)="([^"]*)"', m.group(1)))
    # Chromium's stderr log carries console messages as `...:CONSOLE:<line>] "text", source: ...`
    # without their level; the report writes nothing to the console, so any message is a finding
    # (CSP violations, failed loads, uncaught exceptions, console.error/warn/log).
    console = [ln for ln in proc.stderr.splitlines() if ":CONSOLE" in ln]
    return attrs, console


def test_console_capture_detects_errors(tmp_path):
    """The detection itself must work: a broken page is caught."""
    exe = _chromium()
    bad = tmp_path / "bad.html"
    bad.write_text(
        "<!DOCTYPE html><html><head><meta http-equiv=\"Content-Security-Policy\" "
        "content=\"default-src 'none'; img-src data:; script-src 'unsafe-inline'\"></head>"
        "<body data-figures-expected=\"1\"><img data-figure=\"x\" src=\"http://example.invalid/a.png\">"
        "<script>console.error('deliberate'); throw new Error('boom');</script>"
        "<script>" + (pathlib.Path(__file__).resolve().parent.parent / "vsidgen" / "report" /
                      "templates" / "report_check.js.j2").read_text() + "</script></body></html>")
    attrs, console = _load(exe, tmp_path, bad, "bad")
    text = "\n".join(console)
    assert "deliberate" in text and "boom" in text and "Content Security Policy" in text
    assert attrs.get("data-figures-ok") == "false"
    assert attrs.get("data-figures-broken") == "x"


def test_report_renders_in_headless_chromium(tmp_path):
    exe = _chromium()
    d = write_results_dir(tmp_path / "fit", n_samples=300)
    page = write_report(d)
    attrs, console = _load(exe, tmp_path, page, "report")
    assert console == [], "console messages:\n" + "\n".join(console)
    expected = 1 + 2 * (2 * len(OUTPUTS) + len(STATES))
    assert attrs.get("data-figures-expected") == str(expected)
    assert attrs.get("data-figure-count") == str(expected)
    assert attrs.get("data-figures-broken") == ""
    assert attrs.get("data-js-errors") == "0"
    assert attrs.get("data-figures-ok") == "true", attrs
    assert int(attrs.get("data-equation-count", "0")) >= 10

    shot = tmp_path / "report_screenshot.png"
    proc = _run(exe, tmp_path, "shot", "--window-size=1400,3000", f"--screenshot={shot}",
                page.as_uri())
    assert proc.returncode == 0 and shot.is_file(), proc.stderr[-2000:]
    raw = shot.read_bytes()
    assert raw[:8] == b"\x89PNG\r\n\x1a\n" and len(raw) > 50_000   # not a blank page
    if os.environ.get("VSIDGEN_SAVE_SCREENSHOT") == "1":
        dest = pathlib.Path(__file__).resolve().parent.parent / "docs" / "report_screenshot.png"
        shutil.copyfile(shot, dest)
