"""Locked dependencies: one lock per platform under ``locks/``, exact versions with sha256 hashes, made by
``uv pip compile`` (``make lock``) and installed by pip with ``--require-hashes`` (``make setup``, k8s/Dockerfile).

A lock is named ``<kind>-<system>-<machine>-py<XY>.txt``: ``cpu`` (this package with ``dev``, torch's CPU build;
``make setup`` where there is no GPU), ``cuda`` (with ``gpu`` and ``dev``, PyPI's CUDA build of torch; ``make setup``
on a GPU machine and the Ray image) and ``mlflow`` (the MLflow server image: ``mlflow[auth]`` at the client's
version, the Postgres driver, boto3). Each kind's inputs are pyproject.toml's ``[project]`` dependencies and the
kind's extras, plus ``locks/<kind>.in`` (the torch build, and the tools ``make setup`` installs with: pip,
setuptools, wheel). ``make lock`` stamps a digest of those inputs into the lock, so a dependency edited in
pyproject.toml without ``make lock`` is caught by ``tests/gdwm/test_environment_lock.py``.

Run as a script (``python platform/gdwm/environment/lock.py name``, before any venv exists) it prints this machine's
lock name with the standard library alone; ``python -m gdwm.environment.lock sync|compile|check`` are ``make``'s.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

STAMP = ".installed"
"""``make setup``'s stamp in the venv (``sys.prefix``): it holds the path of the lock the venv was made from."""
LOCK_ENV = "GDWM_LOCK"
"""A lock's path, for an environment installed from a lock without ``make setup`` (the Ray image sets it)."""


@dataclass(frozen=True)
class Kind:
    extras: tuple[str, ...]
    """pyproject.toml extras locked with ``[project]`` dependencies (None: pyproject.toml is no input)."""
    pyproject: bool = True
    constrained_by: str | None = None
    """Another kind of the same platform whose lock pins what both share (the server's MLflow = the client's)."""


KINDS = {
    "cpu": Kind(("dev",)),
    "cuda": Kind(("gpu", "dev")),
    "mlflow": Kind((), pyproject=False, constrained_by="cpu"),
}


def this_machine() -> str:
    """The lock name of this machine: ``cuda`` where ``nvidia-smi`` is on PATH (a CUDA driver), else ``cpu``."""
    kind = "cuda" if shutil.which("nvidia-smi") else "cpu"
    py = f"py{sys.version_info[0]}{sys.version_info[1]}"
    return f"{kind}-{platform.system().lower()}-{platform.machine()}-{py}"


def parse_name(name: str) -> tuple[str, str, str, str]:
    """``cpu-linux-x86_64-py311`` -> (kind, system, machine, python version ``3.11``)."""
    m = re.fullmatch(r"(?P<kind>[a-z]+)-(?P<system>[a-z]+)-(?P<machine>\w+)-py(?P<major>\d)(?P<minor>\d+)", name)
    if m is None or m["kind"] not in KINDS:
        raise ValueError(f"lock name '{name}': expected <kind>-<system>-<machine>-py<XY> with kind one of "
                         f"{', '.join(KINDS)} (e.g. cpu-linux-x86_64-py311)")  # fmt: skip
    return m["kind"], m["system"], m["machine"], f"{m['major']}.{m['minor']}"


# ---- reading a lock ------------------------------------------------------------------------------------------------
def canonical(name: str) -> str:
    """PEP 503's normalised name: ``Jinja2`` and ``jinja2``, ``ruamel.yaml`` and ``ruamel-yaml`` are one."""
    return re.sub(r"[-_.]+", "-", name).lower()


_PIN = re.compile(r"^(?P<name>[A-Za-z0-9][A-Za-z0-9._-]*)(?:\[[^\]]*\])?==(?P<version>[^\s;\\]+)")
_DIGEST = re.compile(r"^# gdwm inputs sha256:(?P<digest>[0-9a-f]{64})")


@dataclass
class Lock:
    path: Path
    pins: dict[str, str] = field(default_factory=dict)
    """Canonical name -> exact version."""
    direct: set[str] = field(default_factory=set)
    """Names the lock's inputs ask for themselves (uv's ``# via`` names pyproject.toml or a ``.in`` file)."""
    inputs: str | None = None
    """The digest of the inputs ``make lock`` stamped (``inputs_digest``); None in a lock made otherwise."""

    @property
    def name(self) -> str:
        return self.path.name.removesuffix(".txt")

    @property
    def sha256(self) -> str:
        return hashlib.sha256(self.path.read_bytes()).hexdigest()


def _names_an_input(via: str) -> bool:
    """uv's ``# via`` line names pyproject.toml (``gdwm (pyproject.toml)``) or a ``.in`` file (``-r locks/cpu.in``)."""
    return "(pyproject.toml)" in via or via.split()[-1].endswith(".in")


def read_lock(path: Path) -> Lock:
    lock = Lock(Path(path))
    current = None
    for line in lock.path.read_text().splitlines():
        if m := _DIGEST.match(line):
            lock.inputs = m["digest"]
        elif m := _PIN.match(line):
            current = canonical(m["name"])
            lock.pins[current] = m["version"]
        elif current and line.strip().startswith("#") and _names_an_input(line):
            lock.direct.add(current)
    return lock


# ---- what is installed ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Installed:
    version: str
    editable: bool
    """Installed from a working tree (``pip install -e``): the user's own code, never in a lock."""


def installed() -> dict[str, Installed]:
    """Every distribution importable here (canonical name -> version): the first of a name on ``sys.path``, the one
    ``importlib.metadata`` (and an import) resolves; a name installed editable anywhere on it counts as editable (the
    ``<name>.egg-info`` an editable build leaves in the checkout is that install). Copies a package vendors inside
    site-packages (Ray's ``thirdparty_files``) are that package's, not installs."""
    import importlib.metadata as md
    import site

    sites = [Path(p).resolve() for p in site.getsitepackages()]
    out: dict[str, Installed] = {}
    for entry in sys.path:
        where = Path(entry or ".").resolve()
        if any(s in where.parents for s in sites) or not where.is_dir():
            continue
        for meta in sorted(where.glob("*.*-info")):
            # ``name-version.dist-info`` names both (the wheel spec): 190 distributions in 10 ms, not 0.5 s of
            # METADATA parsing; anything else (an egg-info) is read
            name, _, version = meta.name.rsplit(".", 1)[0].partition("-")
            if meta.suffix != ".dist-info" or not version:
                dist = md.Distribution.at(meta)
                name, version = dist.metadata["Name"], dist.version
            if not name:
                continue
            direct = meta / "direct_url.json"
            editable = direct.is_file() and json.loads(direct.read_text()).get("dir_info", {}).get("editable", False)
            first = out.setdefault(canonical(name), Installed(version, editable))
            if editable and not first.editable:
                out[canonical(name)] = Installed(first.version, True)
    return out


@dataclass
class Drift:
    """How the installed distributions differ from a lock."""

    missing: dict[str, str] = field(default_factory=dict)
    """Locked, not installed: name -> locked version."""
    other: dict[str, tuple[str, str]] = field(default_factory=dict)
    """Installed at another version: name -> (locked, installed)."""
    extra: dict[str, str] = field(default_factory=dict)
    """Installed, not locked (editable installs aside): name -> version."""

    def __bool__(self) -> bool:
        return bool(self.missing or self.other or self.extra)

    def lines(self) -> list[str]:
        return (
            [f"{n} {v} is locked but not installed" for n, v in sorted(self.missing.items())]
            + [f"{n} is {i}, the lock says {lk}" for n, (lk, i) in sorted(self.other.items())]
            + [f"{n} {v} is installed but not locked" for n, v in sorted(self.extra.items())]
        )


def drift(lock: Lock, have: dict[str, Installed] | None = None) -> Drift:
    have = installed() if have is None else have
    d = Drift()
    for name, version in lock.pins.items():
        if name not in have:
            d.missing[name] = version
        elif have[name].version != version:
            d.other[name] = (version, have[name].version)
    d.extra = {n: i.version for n, i in have.items() if n not in lock.pins and not i.editable}
    return d


def venv_lock() -> Path | None:
    """The lock this environment was installed from: ``$GDWM_LOCK``, else the one ``make setup`` wrote in its stamp;
    None when neither says (an environment made otherwise)."""
    if os.environ.get(LOCK_ENV):
        return Path(os.environ[LOCK_ENV])
    stamp = Path(sys.prefix) / STAMP
    text = stamp.read_text().strip() if stamp.is_file() else ""
    return Path(text) if text else None


# ---- the lock's inputs ---------------------------------------------------------------------------------------------
def inputs_digest(repo: Path, kind: str) -> str:
    """sha256 of what a lock of ``kind`` is compiled from: pyproject.toml's requirements (dependencies, the kind's
    extras, build-system, requires-python) and ``locks/<kind>.in``'s lines; comments and order do not count."""
    spec = KINDS[kind]
    payload: dict = {"in": sorted(_requirement_lines(repo / "locks" / f"{kind}.in"))}
    if spec.pyproject:
        project = tomllib.loads((repo / "pyproject.toml").read_text())
        payload |= {
            "dependencies": sorted(project["project"]["dependencies"]),
            "extras": {e: sorted(project["project"]["optional-dependencies"].get(e, [])) for e in spec.extras},
            "build": sorted(project["build-system"]["requires"]),
            "python": project["project"].get("requires-python", ""),
        }
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def _requirement_lines(path: Path) -> list[str]:
    lines = (ln.split("#", 1)[0].strip() for ln in path.read_text().splitlines())
    return [ln for ln in lines if ln]


def requirements(repo: Path, kind: str) -> list[str]:
    """The requirement strings a lock of ``kind`` must satisfy (pyproject.toml's, its extras', build-system's, the
    ``.in`` file's)."""
    spec = KINDS[kind]
    out = list(_requirement_lines(repo / "locks" / f"{kind}.in"))
    if spec.pyproject:
        project = tomllib.loads((repo / "pyproject.toml").read_text())
        out += project["project"]["dependencies"] + project["build-system"]["requires"]
        for e in spec.extras:
            out += project["project"]["optional-dependencies"].get(e, [])
    return out


def disagreements(repo: Path, lock: Lock) -> list[str]:
    """Why ``lock`` no longer fits pyproject.toml and its ``.in`` file: a requirement it lacks or pins outside the
    requirement's range, a direct dependency nothing asks for any more, inputs changed since ``make lock``."""
    from packaging.markers import default_environment
    from packaging.requirements import Requirement

    kind, system, machine, py = parse_name(lock.name)
    env = default_environment() | {"python_version": py, "platform_machine": machine,
                                   "sys_platform": system, "platform_system": system.capitalize()}  # fmt: skip
    out, asked = [], set()
    for text in requirements(repo, kind):
        req = Requirement(text)
        if req.marker is not None and not req.marker.evaluate(env | {"extra": ""}):
            continue
        name = canonical(req.name)
        asked.add(name)
        if name not in lock.pins:
            out.append(f"{req.name}: required ({text}) but not in {lock.path.name}")
        elif not req.specifier.contains(lock.pins[name], prereleases=True):
            out.append(f"{req.name}: required {req.specifier}, {lock.path.name} pins {lock.pins[name]}")
    for name in sorted(lock.direct - asked):
        out.append(f"{name}: {lock.path.name} locks it as a direct dependency, which nothing asks for any more")
    if lock.inputs != inputs_digest(repo, kind):
        what = "pyproject.toml's requirements or " if KINDS[kind].pyproject else ""
        out.append(f"{lock.path.name}: {what}locks/{kind}.in changed since it was made")
    return out


# ---- making a lock -------------------------------------------------------------------------------------------------
def compile_lock(repo: Path, name: str) -> Path:
    """``locks/<name>.txt`` from its inputs with ``uv pip compile`` for that platform, stamped with the inputs'
    digest. torch's CPU build comes from ``$TORCH_CPU_WHEELS`` (a directory or page of wheels), else pip's
    find-links (``$PIP_FIND_LINKS``), else PyTorch's index page."""
    from uv import find_uv_bin

    kind, system, machine, py = parse_name(name)
    spec = KINDS[kind]
    out = repo / "locks" / f"{name}.txt"
    target = {"linux": f"{machine}-manylinux_2_28", "darwin": f"{machine}-apple-darwin"}.get(system)
    if target is None:
        raise ValueError(f"lock name '{name}': no uv platform for system '{system}' (linux or darwin)")
    cmd = [find_uv_bin(), "pip", "compile", "--quiet", "--generate-hashes", "--python-version", py,
           "--python-platform", target, "--custom-compile-command", "make lock", "-o", str(out)]  # fmt: skip
    if spec.pyproject:
        cmd += ["pyproject.toml", *(f"--extra={e}" for e in spec.extras)]
    cmd.append(f"locks/{kind}.in")
    if spec.constrained_by:
        cmd += ["-c", f"locks/{spec.constrained_by}-{system}-{machine}-py{py.replace('.', '')}.txt"]
    if kind == "cpu":
        wheels = os.environ.get("TORCH_CPU_WHEELS") or os.environ.get("PIP_FIND_LINKS")
        for where in (wheels or "https://download.pytorch.org/whl/cpu/torch/").split():
            cmd += ["--find-links", where]
    subprocess.run(cmd, cwd=repo, check=True)
    lines = out.read_text().splitlines(keepends=True)
    head = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    stamp = f"# gdwm inputs sha256:{inputs_digest(repo, kind)} (checked by tests/gdwm/test_environment_lock.py)\n"
    out.write_text("".join([*lines[:head], stamp, *lines[head:]]))
    return out


# ---- make's entry points -------------------------------------------------------------------------------------------
def sync(lock_path: Path) -> int:
    """After ``pip install --require-hashes -r LOCK``: uninstall what the lock does not hold (editable installs,
    the user's own code, stay), then fail naming any distribution that still differs."""
    lock = read_lock(lock_path)
    d = drift(lock)
    if d.extra:
        names = sorted(d.extra)
        print(f"make setup: removing what {lock.path.name} does not hold: "
              + ", ".join(f"{n} {d.extra[n]}" for n in names))  # fmt: skip
        subprocess.run([sys.executable, "-m", "pip", "uninstall", "--yes", "--quiet", *names], check=True)
        d = drift(lock)
    if d:
        print(f"make setup: the environment differs from {lock.path}: " + "; ".join(d.lines()), file=sys.stderr)
        return 1
    return 0


def main(argv: list[str]) -> int:
    if argv[:1] == ["name"]:
        print(this_machine())
        return 0
    repo = Path.cwd()
    if argv[:1] == ["sync"] and len(argv) == 2:
        return sync(Path(argv[1]))
    if argv[:1] == ["compile"] and len(argv) > 1:
        # a constrained kind reads the lock it is constrained by: make that one first
        for name in sorted(argv[1:], key=lambda n: KINDS[parse_name(n)[0]].constrained_by is not None):
            print(f"locked {compile_lock(repo, name).relative_to(repo)}")
        return 0
    if argv[:1] == ["check"]:
        problems = [p for path in sorted((repo / "locks").glob("*.txt")) for p in disagreements(repo, read_lock(path))]
        for p in problems:
            print(p, file=sys.stderr)
        return 1 if problems else 0
    print("usage: lock.py name | sync LOCK | compile NAME... | check", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
