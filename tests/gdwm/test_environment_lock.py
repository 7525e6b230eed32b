"""Locked dependencies (gdwm.environment.lock): the venv is exactly its lock, every lock agrees with pyproject.toml,
a disagreement is named, and ``make setup`` on a machine without a lock says in one line what to run."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from gdwm.environment.lock import (
    Installed,
    canonical,
    disagreements,
    drift,
    inputs_digest,
    installed,
    read_lock,
    this_machine,
    venv_lock,
)

REPO = Path(__file__).resolve().parents[2]
LOCKS = sorted((REPO / "locks").glob("*.txt"))


def test_the_venv_holds_exactly_the_locked_versions():
    """Must show: `make setup` installs exactly the lock's versions (in a venv it made: its stamp names the lock)."""
    path = venv_lock()
    if path is None:
        pytest.skip(f"{sys.prefix} was not made by `make setup` from a lock (no lock in its .installed stamp)")
    lock = read_lock(path)
    d = drift(lock)
    assert not d, f"the environment differs from {path.name}:\n  " + "\n  ".join(d.lines())
    have = installed()
    assert have["torch"].version == lock.pins["torch"] and len(lock.pins) > 150
    assert have["gdwm"].editable  # this checkout, the one distribution no lock holds


@pytest.mark.parametrize("lock", LOCKS, ids=lambda p: p.name)
def test_every_lock_agrees_with_pyproject(lock):
    assert disagreements(REPO, read_lock(lock)) == []


def test_the_locks_cover_this_machine_and_the_image():
    names = {p.name.removesuffix(".txt") for p in LOCKS}
    assert {"cpu-linux-x86_64-py311", "cuda-linux-x86_64-py311", "mlflow-linux-x86_64-py311"} <= names
    cpu, cuda, server = (read_lock(REPO / "locks" / f"{k}-linux-x86_64-py311.txt") for k in ("cpu", "cuda", "mlflow"))
    assert cpu.pins["torch"].endswith("+cpu") and "+" not in cuda.pins["torch"]
    assert cpu.pins["torch"].split("+")[0] == cuda.pins["torch"]
    # the server's MLflow is the client's; every other package both locks hold is at one version
    assert server.pins["mlflow"] == cpu.pins["mlflow"] == cuda.pins["mlflow"]
    assert {n for n in cpu.pins.keys() & cuda.pins.keys() if cpu.pins[n] != cuda.pins[n]} == {"torch"}
    assert "gsplat" in cuda.pins and "gsplat" not in cpu.pins
    assert this_machine().endswith(f"-py{sys.version_info[0]}{sys.version_info[1]}")


def _project(tmp_path: Path, edit) -> Path:
    """A copy of the repository's lock inputs with pyproject.toml edited."""
    (tmp_path / "locks").mkdir()
    for p in (REPO / "locks").iterdir():
        shutil.copy(p, tmp_path / "locks" / p.name)
    text = (REPO / "pyproject.toml").read_text()
    (tmp_path / "pyproject.toml").write_text(edit(text))
    return tmp_path


def test_a_range_the_lock_misses_is_named(tmp_path):
    root = _project(tmp_path, lambda t: t.replace('"torch>=2.6,<2.15"', '"torch>=2.14,<2.15"'))
    lock = read_lock(root / "locks" / "cpu-linux-x86_64-py311.txt")
    assert disagreements(root, lock) == [
        "torch: required <2.15,>=2.14, cpu-linux-x86_64-py311.txt pins 2.13.0+cpu",
        "cpu-linux-x86_64-py311.txt: pyproject.toml's requirements or locks/cpu.in changed since it was made",
    ]


def test_an_added_and_a_removed_dependency_are_named(tmp_path):
    root = _project(tmp_path, lambda t: t.replace('    "scipy>=1.11",\n', '    "polars>=1",\n'))
    lock = read_lock(root / "locks" / "cpu-linux-x86_64-py311.txt")
    problems = disagreements(root, lock)
    assert "polars: required (polars>=1) but not in cpu-linux-x86_64-py311.txt" in problems
    assert ("scipy: cpu-linux-x86_64-py311.txt locks it as a direct dependency, which nothing asks for any more"
            in problems)  # fmt: skip
    assert inputs_digest(root, "cpu") != inputs_digest(REPO, "cpu")


def test_comments_and_order_do_not_change_the_inputs(tmp_path):
    root = _project(tmp_path, lambda t: t.replace('    "scipy>=1.11",\n', "").replace(
        '    "numpy>=1.26,<3",\n', '    "scipy>=1.11",  # moved\n    "numpy>=1.26,<3",\n'))  # fmt: skip
    assert inputs_digest(root, "cpu") == inputs_digest(REPO, "cpu")


def test_drift_names_missing_other_and_extra_distributions():
    lock = read_lock(LOCKS[0])
    lock.pins = {"numpy": "2.3.0", "torch": "2.13.0+cpu", "scipy": "1.16.0"}
    have = {"numpy": Installed("2.3.0", False), "torch": Installed("2.14.0", False),
            "pyinstrument": Installed("5.1.3", False), "myplugin": Installed("0.1", True)}  # fmt: skip
    assert drift(lock, have).lines() == [
        "scipy 1.16.0 is locked but not installed",
        "torch is 2.14.0, the lock says 2.13.0+cpu",
        "pyinstrument 5.1.3 is installed but not locked",  # an editable plugin is the user's own code: not listed
    ]
    assert canonical("Ruamel.YAML") == canonical("ruamel_yaml") == "ruamel-yaml"


def test_make_setup_without_a_lock_for_this_machine_says_what_to_run(tmp_path):
    # a GPU machine (nvidia-smi on PATH) with only the CPU lock: one line, nothing installed
    for rel in ("Makefile", "pyproject.toml", "platform/gdwm/environment/lock.py", "locks/cpu-linux-x86_64-py311.txt"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(REPO / rel, tmp_path / rel)
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "nvidia-smi").write_text("#!/bin/sh\nexit 0\n")
    (bin_dir / "nvidia-smi").chmod(0o755)
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}"}
    r = subprocess.run(["make", "-s", "setup", f"PYTHON={sys.executable}"], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=60)  # fmt: skip
    name = f"cuda-linux-{os.uname().machine}-py{sys.version_info[0]}{sys.version_info[1]}"
    assert r.returncode == 2, r.stdout + r.stderr
    # make's own error lines aside ("make[1]: ***" when the suite itself runs under make)
    ours = [line for line in r.stderr.splitlines() if not re.match(r"make(\[\d+\])?: \*\*\*", line)]
    assert ours == [
        f"make setup: no lock for this machine (locks/{name}.txt is missing; locks/ has "
        f"cpu-linux-x86_64-py311.txt): run 'make lock LOCKS={name}' where uv reaches PyPI, commit it, then make setup"
    ]
    assert not (tmp_path / ".venv").exists()
