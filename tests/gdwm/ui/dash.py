"""``gdwm ui`` as a user starts it, for the dashboard's tests: a subprocess on a free port (``--port 0``), the URL read
from its first line (printed once the page answers), stopped with SIGTERM; and headless Chromium (the system's
``/usr/bin/chromium`` through playwright, no browser download)."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[3]
CHROMIUM = "/usr/bin/chromium" if Path("/usr/bin/chromium").is_file() else shutil.which("chromium")
URL = re.compile(r"gdwm ui: (http://\S+)")


def env(**extra: str) -> dict[str, str]:
    out = {k: v for k, v in os.environ.items() if not k.startswith("GDWM_TEST_") and k != "RAY_AUTH_MODE"}
    return out | {"PYTHONPATH": str(REPO), "GDWM_CONF_PATH": str(REPO / "tests" / "conf")} | extra


class Dashboard:
    def __init__(self, proc: subprocess.Popen, url: str, lines: list[str]):
        self.proc, self.url, self.lines = proc, url, lines

    @property
    def base(self) -> str:
        return self.url.split("/sweeps/")[0].rstrip("/")


@contextmanager
def dashboard(*overrides: str, timeout_s: float = 300, **extra_env: str) -> Iterator[Dashboard]:
    """``gdwm ui --port 0 OVERRIDES`` until the block ends; fails with its output if it exits first."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "gdwm", "ui", "--port", "0", *overrides],
        env=env(**extra_env),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    lines: list[str] = []
    found = threading.Event()

    def read() -> None:
        for line in proc.stdout:
            lines.append(line)
            if line.startswith("gdwm ui:"):  # its URL, or why the page did not answer
                found.set()
        found.set()

    threading.Thread(target=read, daemon=True).start()
    try:
        found.wait(timeout_s)
        match = next((URL.search(x) for x in lines if URL.search(x)), None)
        if match is None:
            pytest.fail(f"gdwm ui printed no URL (exit {proc.poll()}):\n{''.join(lines)[-3000:]}")
        yield Dashboard(proc, match.group(1), lines)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                proc.kill()


@contextmanager
def browser() -> Iterator:
    """A headless Chromium page at 1280 x 900."""
    playwright = pytest.importorskip("playwright.sync_api", reason="playwright is not installed")
    if CHROMIUM is None:
        pytest.skip("chromium is not installed (apt-get install chromium)")
    with playwright.sync_playwright() as p:
        b = p.chromium.launch(headless=True, executable_path=CHROMIUM)
        try:
            yield b.new_page(viewport={"width": 1280, "height": 900})
        finally:
            b.close()
