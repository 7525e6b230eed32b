"""A machine that cannot work says so in one line, at once: a full TMPDIR before Ray starts (Ray's own symptom is a
timeout a minute later), a read-only HOME naming the path and what to change."""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

import pytest

from gdwm.preflight import RAY_TMP_NEEDS, check_ray_temp, writable_space
from tests.gdwm.test_run import Toy


@pytest.fixture
def mount(tmp_path):
    """``mount(target, *options)`` (a real mount: a tiny tmpfs, a read-only bind), undone after the test; skips
    where this process may not mount (not root, no CAP_SYS_ADMIN)."""
    done: list[Path] = []

    def _mount(target: Path, *args: str) -> Path:
        target.mkdir(parents=True, exist_ok=True)
        r = subprocess.run(["mount", *args, str(target)], capture_output=True, text=True)
        if r.returncode != 0:
            pytest.skip(f"cannot mount here ({r.stderr.strip()})")
        done.append(target)
        return target

    yield _mount
    for target in reversed(done):
        subprocess.run(["umount", "-l", str(target)], capture_output=True)


def test_space_is_measured_and_probed(tmp_path, monkeypatch):
    assert writable_space(tmp_path, 1) is None
    assert writable_space(tmp_path, 10**18).startswith(f"{tmp_path} has only ")  # more than any disk holds
    monkeypatch.setenv("RAY_TMPDIR", str(tmp_path / "ray-here"))
    assert check_ray_temp() is None and (tmp_path / "ray-here").is_dir()


def test_a_full_tmpdir_fails_before_ray_starts_with_one_line(tmp_path, mount):
    full = mount(tmp_path / "full", "-t", "tmpfs", "-o", "size=1m", "tmpfs")
    with open(full / "fill", "wb") as f:
        try:
            while True:
                f.write(b"\0" * 65536)
        except OSError:  # no space left: as full as a disk gets
            pass
    toy = Toy(tmp_path / "toy")
    t0 = time.monotonic()
    r = subprocess.run(toy.args("targets=[reconstruct]", "run.live=false"), env={**toy.env(), "TMPDIR": str(full)},
                       capture_output=True, text=True, timeout=300)  # fmt: skip
    took = time.monotonic() - t0
    assert r.returncode == 1, r.stderr[-2000:]
    assert r.stderr.strip().splitlines()[-1] == (
        f"gdwm run: TMPDIR: {full} has only 0.0 MB free ({RAY_TMP_NEEDS / 1e6:.1f} MB needed); Ray keeps its session "
        "files there: free some space or point TMPDIR at another disk"
    )
    assert "Timed out waiting for file" not in r.stderr and took < 30


def test_a_read_only_home_is_named_with_what_to_change(tmp_path, mount):
    home = mount(tmp_path / "home", "--bind", str(tmp_path / "home"))
    subprocess.run(["mount", "-o", "remount,bind,ro", str(home)], check=True)
    toy = Toy(tmp_path / "toy")
    r = subprocess.run(toy.args("targets=[reconstruct]", "run.live=false"), env={**toy.env(), "HOME": str(home)},
                       capture_output=True, text=True, timeout=300)  # fmt: skip
    assert r.returncode == 1, r.stderr[-2000:]
    assert r.stderr.strip().splitlines()[-1] == (
        f"gdwm run: {home}/.ray: Read-only file system; it is under HOME ({home}), which gdwm and Ray write to: point "
        "HOME at a writable directory"
    )
