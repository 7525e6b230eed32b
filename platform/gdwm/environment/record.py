"""What a launch ran in: gdwm's commit (and whether the tree was dirty, with a hash of the diff), Python, every
installed distribution and its version, torch's build, thread counts, the CPU (model and the kernels torch picks,
``torch.backends.cpu.get_cpu_capability()``), GPUs with driver and CUDA where present, and the lock the environment
was installed from (with what differs from it).

The record is computed once per process (a launch is one process) and its **digest** -- sha256 of everything but
the code, the host and the time, 12 hex digits -- names the environment: two runs with one digest ran the same
software on the same kind of machine, so the same config gives the same numbers (tests/pipelines/
test_determinism.py); another digest explains why they may move (float rounding on another CPU or library).
gdwm's commit is recorded but left out of the digest: what code a stage ran is in its cache key already (its code
fingerprint), and a README edit must not make every later run "another environment".
"""

from __future__ import annotations

import contextlib
import datetime
import functools
import hashlib
import importlib.metadata
import importlib.util
import json
import os
import platform
import shutil
import socket
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from gdwm.environment.lock import drift, installed, read_lock, venv_lock
from gdwm.localdir import local_dir

SCHEMA = 1
COMMIT_ENV = "GDWM_COMMIT"
"""gdwm's commit where the source is no git checkout (the Ray image bakes it in at build time)."""
THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "CUBLAS_WORKSPACE_CONFIG")
"""Environment variables that change how many threads (or which cuBLAS workspace) kernels use."""
UNDIGESTED = ("digest", "recorded_at", "host", "gdwm", "lock", "kernel", "launch", "driver")
"""Fields that describe the record, the code or the launch, not the environment: left out of the digest."""


def collect() -> dict[str, Any]:
    """This process's environment (``environment()`` keeps it for the process)."""
    facts = torch_facts()
    rec: dict[str, Any] = {
        "schema": SCHEMA,
        "recorded_at": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "host": socket.gethostname(),
        "gdwm": code_state(),
        "python": {"version": platform.python_version(), "implementation": platform.python_implementation()},
        "os": {"system": platform.system(), "machine": platform.machine(), "libc": " ".join(platform.libc_ver())},
        "kernel": platform.release(),
        "cpu": {
            "model": cpu_model(),
            "logical": os.cpu_count(),
            "usable": len(_usable_cpus()),
            "capability": facts["capability"],
        },
        "threads": {**facts["threads"], **{v: os.environ[v] for v in THREAD_VARS if v in os.environ}},
        "torch": facts["torch"],
        "gpu": gpus(),
        "distributions": {},
        "editable": [],
    }
    have = installed()
    rec["distributions"] = {n: i.version for n, i in sorted(have.items())}
    rec["editable"] = sorted(n for n, i in have.items() if i.editable)
    rec["ray"] = rec["distributions"].get("ray")
    rec["mlflow"] = rec["distributions"].get("mlflow")
    rec["lock"] = lock_state(have)
    rec["digest"] = digest(rec)
    return rec


@functools.cache
def environment() -> dict[str, Any]:
    """This process's record, computed on the first call (about 0.1 s with torch imported; ``benchmarks``)."""
    return collect()


def digest(rec: dict[str, Any]) -> str:
    body = {k: v for k, v in rec.items() if k not in UNDIGESTED}
    return hashlib.sha256(json.dumps(body, sort_keys=True, default=str).encode()).hexdigest()[:12]


# ---- the parts -------------------------------------------------------------------------------------------------
def _usable_cpus() -> list[int]:
    return sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else list(range(os.cpu_count() or 1))


def torch_facts() -> dict[str, Any]:
    """torch's build, its thread counts and the CPU kernels it picks. A process without torch imported reads them
    from the file written when they were last computed for this very install (torch's files and version, this
    Python, the variables that set thread counts, the CPUs this process may use): a launch's driver uses no torch,
    and importing it only for this is about 2 s of CPU at every launch."""
    if "torch" in sys.modules:  # this process's own, as they are now (a stage may have set its thread count)
        return _torch_facts(sys.modules["torch"])
    key = _torch_install_key()
    path = local_dir() / "environment" / f"torch-{key}.json" if key else None
    if path is not None:
        with contextlib.suppress(OSError, ValueError):
            return json.loads(path.read_text())
    import torch

    facts = _torch_facts(torch)
    if path is not None:
        with contextlib.suppress(OSError):  # best effort, atomic: a concurrent writer writes the same
            path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=".torch-", dir=path.parent)
            with os.fdopen(fd, "w") as f:
                json.dump(facts, f)
            os.replace(tmp, path)
    return facts


def _torch_facts(torch) -> dict[str, Any]:
    return {
        "capability": torch.backends.cpu.get_cpu_capability(),
        "threads": {"torch": torch.get_num_threads(), "torch_interop": torch.get_num_interop_threads()},
        "torch": {
            "version": torch.__version__,
            "git": torch.version.git_version,
            "cuda": torch.version.cuda,
            "cudnn": torch.backends.cudnn.version() if torch.backends.cudnn.is_available() else None,
            "debug": torch.version.debug,
            # BLAS/LAPACK/oneDNN versions and build flags: what one version number does not say
            "config": torch.__config__.show(),
        },
    }


def _torch_install_key() -> str | None:
    """What torch's facts depend on, hashed; None where torch is not installed as files (then it is imported)."""
    spec = importlib.util.find_spec("torch")
    if spec is None or not spec.origin or not os.path.isfile(spec.origin):
        return None
    root = Path(spec.origin).parent
    parts: list[Any] = [sys.executable, sys.version, importlib.metadata.version("torch"), _usable_cpus(), cpu_model()]
    for name in ("__init__.py", "version.py", "lib"):
        with contextlib.suppress(OSError):
            st = (root / name).stat()
            parts.append([name, st.st_size, st.st_mtime_ns, st.st_ino])
    parts.append({v: os.environ.get(v) for v in (*THREAD_VARS, "OMP_DYNAMIC", "MKL_DYNAMIC")})
    return hashlib.sha256(json.dumps(parts, default=str).encode()).hexdigest()[:16]


def source_root() -> Path:
    """The checkout gdwm runs from (platform/gdwm/.. /..): a git work tree, or an installed wheel's site-packages."""
    return Path(__file__).resolve().parents[3]


def _git(root: Path, *args: str) -> bytes | None:
    if shutil.which("git") is None:
        return None
    r = subprocess.run(["git", "-C", str(root), *args], capture_output=True, timeout=30)
    return r.stdout if r.returncode == 0 else None


def code_state(root: Path | None = None) -> dict[str, Any]:
    """gdwm's commit, whether the tree differs from it, and sha256 of the difference (the diff against HEAD, binary
    files included, and every untracked file that is not ignored: name and bytes). Outside a git checkout the
    commit is ``$GDWM_COMMIT`` (or null) and nothing is known of a diff."""
    root = source_root() if root is None else root
    head = _git(root, "rev-parse", "HEAD") if (root / ".git").exists() else None
    if head is None:
        return {"commit": os.environ.get(COMMIT_ENV) or None, "dirty": None, "diff_sha256": None}
    h = hashlib.sha256(_git(root, "diff", "HEAD", "--binary") or b"")
    untracked = (_git(root, "ls-files", "--others", "--exclude-standard", "-z") or b"").split(b"\0")
    for name in sorted(n for n in untracked if n):
        h.update(b"\0" + name + b"\0")
        path = root / name.decode()
        if path.is_file():
            h.update(path.read_bytes())
    dirty = bool((_git(root, "status", "--porcelain") or b"").strip())
    return {"commit": head.decode().strip(), "dirty": dirty, "diff_sha256": h.hexdigest() if dirty else None}


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith(("model name", "Model", "cpu model")):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def gpus() -> dict[str, Any] | None:
    """GPUs, the driver and CUDA from ``nvidia-smi`` (no CUDA context is opened in this process); None without."""
    if shutil.which("nvidia-smi") is None:
        return None
    query = ["nvidia-smi", "--query-gpu=name,memory.total,driver_version", "--format=csv,noheader"]
    try:
        out = subprocess.run(query, capture_output=True, text=True, timeout=30, check=True).stdout
        head = subprocess.run(["nvidia-smi"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError) as e:
        return {"error": f"nvidia-smi failed: {e}"}
    rows = [[c.strip() for c in line.split(",")] for line in out.splitlines() if line.strip()]
    cuda = next((p.split(":", 1)[1].split()[0] for p in head.split("|") if "CUDA Version" in p), None)
    return {
        "devices": [{"name": r[0], "memory": r[1]} for r in rows],
        "driver": rows[0][2] if rows else None,
        "cuda_driver": cuda,
    }


def lock_state(have) -> dict[str, Any] | None:
    """The lock this environment was installed from, and what differs from it now (first 20 differences)."""
    path = venv_lock()
    if path is None or not path.is_file():
        return None if path is None else {"name": path.name, "error": f"{path} is gone"}
    lock = read_lock(path)
    lines = drift(lock, have).lines()
    return {"name": lock.name, "sha256": lock.sha256[:12], "matches": not lines, "drift": lines[:20]}


def commit_tag(rec: dict[str, Any]) -> str:
    """``3521056c1a2b`` or ``3521056c1a2b+dirty.1f2e3d4c``; ``unknown`` without a commit."""
    code = rec.get("gdwm") or {}
    commit = (code.get("commit") or "unknown")[:12]
    return commit + (f"+dirty.{code['diff_sha256'][:8]}" if code.get("dirty") else "")


def summary(rec: dict[str, Any]) -> str:
    """One line naming an environment: ``Python 3.11.7, torch 2.13.0+cpu, CPU AVX2 (Intel Xeon ...), 2 threads``."""
    gpu = rec.get("gpu") or {}
    devices = gpu.get("devices") or []
    where = (
        f"{len(devices)}x {devices[0]['name']} (driver {gpu.get('driver')}, CUDA {rec['torch'].get('cuda')})"
        if devices
        else f"CPU {rec['cpu']['capability']} ({rec['cpu']['model']}, {rec['cpu']['usable']} cores)"
    )
    return (f"Python {rec['python']['version']}, torch {rec['torch']['version']}, {where}, "
            f"{rec['threads']['torch']} torch threads")  # fmt: skip


if __name__ == "__main__":  # `python -m gdwm.environment.record`: this machine's record
    json.dump(environment(), sys.stdout, indent=1, sort_keys=True)
    print()
