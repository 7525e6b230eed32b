"""The code a stage runs, as a fingerprint that enters its cache key.

A stage's fingerprint covers:

- **First-party code**: the stage's module (and its ``setup``/``score`` functions' modules, and the modules named by
  ``_target_`` values in its config subset), and every first-party module they import, transitively -- imports
  inside functions included, and each package's ``__init__.py`` on the way. First-party means the packages of
  gdwm's distribution and of every distribution that registers gdwm entry points (``first_party``), the package that
  defines the stage (a plugin's package, e.g. one on ``GDWM_CONF_PATH``), and any module whose source is not in the
  interpreter's standard library or site-packages.
  Each module is hashed from its syntax tree without docstrings (``ast.dump``), so comments, docstrings and
  formatting do not count, while any change to what runs does. A module without Python source (a compiled
  extension) cannot be hashed: it enters as ``unhashable`` and the plan says so; bump the stage's ``version`` when
  it changes.
- **Libraries that change numbers**: the installed versions of those in ``NUMERIC_LIBRARIES`` that the closure
  imports, plus whatever the stage declares (``@stage(libraries=[...])``, distribution names).

Not covered, so still the stage's ``version``'s job: data files the code reads at run time, the Python version
(it changes ``ast.dump`` only across minor versions, which then re-runs everything) and libraries outside the list.

Parsing every module is ~0.3 s for the whole pipeline; each file's hash and imports are kept in memory and in
``$GDWM_LOCAL_CACHE/fingerprints.json`` (default ``~/.cache/gdwm``) by (path, size, mtime), so a warm launch only
stats the files (measured by the ``fingerprint`` performance benchmark).
"""

from __future__ import annotations

import ast
import contextlib
import hashlib
import importlib.machinery
import importlib.util
import json
import logging
import os
import sys
import sysconfig
import tempfile
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from functools import cache
from importlib.metadata import PackageNotFoundError, entry_points, packages_distributions, version
from pathlib import Path
from typing import Any

from gdwm.localdir import local_dir

log = logging.getLogger(__name__)


@cache
def first_party() -> frozenset[str]:
    """Top-level packages hashed wherever they are installed: those of gdwm's own distribution and of every
    distribution that plugs into it (registers an entry point in a ``gdwm.*`` group), site-packages included."""
    groups = [g for g in entry_points().groups if g.startswith("gdwm.")]
    dists = {ep.dist.name for g in groups for ep in entry_points(group=g) if ep.dist is not None}
    tops = packages_distributions()
    dists.update(tops.get("gdwm", ()))
    return frozenset({"gdwm"} | {top for top, ds in tops.items() if dists.intersection(ds)})


UNHASHABLE = "unhashable"

NUMERIC_LIBRARIES: Mapping[str, tuple[str, ...]] = {
    # import name -> distributions that may provide it (the first installed one counts)
    "torch": ("torch",),
    "numpy": ("numpy",),
    "scipy": ("scipy",),
    "cv2": ("opencv-contrib-python-headless", "opencv-python-headless", "opencv-contrib-python", "opencv-python"),
    "transformers": ("transformers",),
    "tokenizers": ("tokenizers",),
    "peft": ("peft",),
    "diffusers": ("diffusers",),
    "accelerate": ("accelerate",),
    "safetensors": ("safetensors",),
    "pycocoevalcap": ("pycocoevalcap",),
    "gsplat": ("gsplat",),
}
"""Third-party libraries whose version can change a stage's numbers (kernels, defaults, tokenisation, metric code).
Others (pyarrow, mlflow, ray, hydra, rich) move bytes and orchestrate; a new release of them keeps every entry."""


# ---- one module ----------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ModuleInfo:
    name: str
    path: str
    """Shown in plans and manifests: relative to the directory holding its top-level package (``gdwm/cache.py``)."""
    digest: str
    """sha256 of the docstring-free syntax tree, or ``UNHASHABLE``."""
    imports: tuple[str, ...]
    """Absolute names of the modules it imports (relative imports resolved), ``from a import b`` as ``a`` and
    ``a.b``; names that turn out not to be modules are dropped on resolution."""
    exports: tuple[tuple[str, str], ...] | None = None
    """A facade's ``EXPORTS`` (name, defining module) pairs (see ``closure``); None for any other module."""


class _StripDocstrings(ast.NodeTransformer):
    def _strip(self, node: ast.AST) -> ast.AST:
        body = getattr(node, "body", None)
        first = body[0] if body else None
        if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
            node.body = body[1:] or [ast.Pass()]
        self.generic_visit(node)
        return node

    visit_Module = visit_FunctionDef = visit_AsyncFunctionDef = visit_ClassDef = _strip


def normalized_digest(source: str | bytes | ast.Module, filename: str = "<source>") -> str:
    """sha256 of the module's syntax tree without docstrings: comments, docstrings and formatting don't count."""
    tree = source if isinstance(source, ast.Module) else ast.parse(source, filename)
    tree = _StripDocstrings().visit(tree)
    return hashlib.sha256(ast.dump(tree, annotate_fields=False, include_attributes=False).encode()).hexdigest()


def _raw_imports(tree: ast.AST) -> list[tuple[int, str, tuple[str, ...]]]:
    """(level, module, names) of every import statement, anywhere in the module."""
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(0, a.name, ()) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            out.append((node.level, node.module or "", tuple(a.name for a in node.names)))
    return out


def _absolute(raw: Iterable[tuple[int, str, tuple[str, ...]]], module: str, is_package: bool) -> tuple[str, ...]:
    package = module if is_package else module.rpartition(".")[0]
    names: set[str] = set()
    for level, mod, items in raw:
        if level:
            base = package.split(".")
            base = base[: len(base) - (level - 1)] if level > 1 else base
            mod = ".".join([*base, mod] if mod else base)
        if not mod:
            continue
        names.add(mod)
        names.update(f"{mod}.{i}" for i in items if i != "*")
    return tuple(sorted(names))


# ---- finding modules without importing them -------------------------------------------------------------------------
@cache
def _site_roots() -> tuple[str, ...]:
    paths = sysconfig.get_paths()
    roots = {paths[k] for k in ("stdlib", "platstdlib", "purelib", "platlib") if k in paths}
    roots |= {p for p in sys.path if p.rstrip("/").endswith(("site-packages", "dist-packages"))}
    return tuple(sorted(os.path.realpath(r) + os.sep for r in roots))


@dataclass(frozen=True)
class _Found:
    path: Path | None
    """The module's source file; None for a compiled or built-in module."""
    is_package: bool
    first_party: bool
    root: Path | None
    """The directory holding the top-level package."""


@cache
def _top(name: str) -> tuple[tuple[Path, ...], Path | None, bool] | None:
    """(search locations, source file, first party) of a top-level module; None when it is not installed."""
    try:  # a top-level name: finding it imports nothing (editable installs need the meta path finders)
        spec = importlib.util.find_spec(name)
    except (ImportError, ValueError):
        return None
    if spec is None:
        return None
    locations = tuple(Path(p) for p in (spec.submodule_search_locations or ()))
    origin = Path(spec.origin) if spec.origin and spec.origin not in ("built-in", "frozen") else None
    where = str(origin.resolve()) if origin else (str(locations[0].resolve()) if locations else "")
    first = name in first_party() or bool(where and not where.startswith(_site_roots()))
    return locations, origin, first


@cache
def _find(name: str, extra_first_party: frozenset[str]) -> _Found | None:
    top, _, rest = name.partition(".")
    found = _top(top)
    if found is None:
        return None
    locations, origin, first = found
    first = first or top in extra_first_party
    if not rest:
        if origin is None:
            return _Found(None, bool(locations), first, locations[0].parent if locations else None)
        return _Found(origin if origin.suffix == ".py" else None, bool(locations), first, origin.parent.parent
                      if origin.name == "__init__.py" else origin.parent)  # fmt: skip
    parts = rest.split(".")
    for loc in locations:  # namespace packages may span several directories
        d = loc.joinpath(*parts[:-1])
        pkg, mod = d / parts[-1], d / f"{parts[-1]}.py"
        if (pkg / "__init__.py").is_file():
            return _Found(pkg / "__init__.py", True, first, loc.parent)
        if mod.is_file():
            return _Found(mod, False, first, loc.parent)
        if any((d / f"{parts[-1]}{suffix}").is_file() for suffix in importlib.machinery.EXTENSION_SUFFIXES):
            return _Found(None, False, first, loc.parent)
        if pkg.is_dir():
            return _Found(None, True, first, loc.parent)  # a namespace package: no code of its own
    return None


# ---- the per-file cache ----------------------------------------------------------------------------------------------
class _FileCache:
    """(path, size, mtime_ns) -> (digest, raw imports): in memory, and on disk between processes."""

    def __init__(self) -> None:
        self.mem: dict[str, list[Any]] = {}
        self.loaded = False
        self.dirty = False

    @staticmethod
    def path() -> Path:
        return local_dir() / f"fingerprints-py{sys.version_info[0]}{sys.version_info[1]}.json"

    def load(self) -> None:
        if self.loaded:
            return
        self.loaded = True
        with contextlib.suppress(OSError, ValueError):
            data = json.loads(self.path().read_text())
            if isinstance(data, dict):
                self.mem.update(data)

    def get(self, path: Path) -> tuple[str, list, dict | None] | None:
        self.load()
        st = path.stat()
        hit = self.mem.get(str(path))
        if hit and len(hit) == 5 and hit[0] == st.st_size and hit[1] == st.st_mtime_ns:  # 4 fields: before facades
            return hit[2], hit[3], hit[4]
        return None

    def put(self, path: Path, digest: str, raw: list, exports: dict | None) -> None:
        st = path.stat()
        self.mem[str(path)] = [st.st_size, st.st_mtime_ns, digest, raw, exports]
        self.dirty = True

    def save(self) -> None:
        """Best effort, atomic: a concurrent launch's copy may win, which only costs it a re-parse."""
        if not self.dirty:
            return
        self.dirty = False
        target = self.path()
        with contextlib.suppress(OSError):
            target.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=".fingerprints-", dir=target.parent)
            with os.fdopen(fd, "w") as f:
                json.dump(self.mem, f)
            os.replace(tmp, target)


_FILES = _FileCache()


def _module(name: str, found: _Found) -> ModuleInfo:
    assert found.root is not None
    shown = (found.path or found.root.joinpath(*name.split("."))).relative_to(found.root).as_posix()
    if found.path is None:
        if found.is_package:  # a namespace package: nothing runs
            return ModuleInfo(name, shown, "namespace", ())
        return ModuleInfo(name, shown, UNHASHABLE, ())
    hit = _FILES.get(found.path)
    if hit is None:
        source = found.path.read_bytes()
        tree = ast.parse(source, str(found.path))
        raw = [[level, mod, list(names)] for level, mod, names in _raw_imports(tree)]
        digest = normalized_digest(tree)
        exports = _facade_exports(tree)
        _FILES.put(found.path, digest, raw, exports)
    else:
        digest, raw, exports = hit
    imports = _absolute(((lvl, m, tuple(n)) for lvl, m, n in raw), name, found.is_package)
    return ModuleInfo(name, shown, digest, imports, None if exports is None else tuple(sorted(exports.items())))


def _facade_exports(tree: ast.Module) -> dict[str, str] | None:
    """``EXPORTS`` (name -> defining module) of a facade module: one that defines a module-level ``__getattr__`` and a
    literal dict ``EXPORTS`` (``gdwm.api``); None for any other module."""
    if not any(isinstance(n, ast.FunctionDef) and n.name == "__getattr__" for n in tree.body):
        return None
    for n in tree.body:
        target = n.targets[0] if isinstance(n, ast.Assign) and len(n.targets) == 1 else getattr(n, "target", None)
        if isinstance(target, ast.Name) and target.id == "EXPORTS" and n.value is not None:
            return dict(ast.literal_eval(n.value))
    return None


def _exports(name: str, found: _Found | None) -> dict[str, str] | None:
    """A first-party facade's exports, from the per-file cache (a warm launch parses nothing)."""
    if found is None or found.path is None or not found.first_party:
        return None
    exports = _module(name, found).exports
    return None if exports is None else dict(exports)


def closure(modules: Iterable[str], extra_first_party: Iterable[str] = ()) -> tuple[dict[str, ModuleInfo], set[str]]:
    """Every first-party module reachable from ``modules`` by imports (parent packages included), and the
    top-level names of the third-party modules they import.

    A name imported from a facade (``from gdwm.api import TrainSession``) counts as an import of the module that
    defines it; the facade's own code and imports do not count (it only hands names on)."""
    extra = frozenset(extra_first_party)
    seen: dict[str, ModuleInfo] = {}
    third: set[str] = set()
    todo = list(modules)
    visited: set[str] = set()
    while todo:
        name = todo.pop()
        if name in visited:
            continue
        visited.add(name)
        found = _find(name, extra)
        if found is None:  # ``from pkg import function``: not a module, unless a facade hands it on
            parent, _, attr = name.rpartition(".")
            exports = _exports(parent, _find(parent, extra)) if parent else None
            if exports is not None and attr in exports:
                todo.append(exports[attr])
            continue
        if not found.first_party:
            third.add(name.partition(".")[0])
            continue
        info = _module(name, found)
        if info.exports is not None:
            continue
        seen[name] = info
        parts = name.split(".")
        todo += [".".join(parts[:i]) for i in range(1, len(parts))]
        todo += info.imports
    return seen, third


# ---- a stage's fingerprint -----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CodeFingerprint:
    digest: str
    files: dict[str, str] = field(default_factory=dict)
    """Module file (``mypackage/stages/train.py``) -> its normalised hash."""
    libraries: dict[str, str] = field(default_factory=dict)
    """Distribution -> installed version (``absent`` when declared but not installed)."""

    @property
    def unhashable(self) -> list[str]:
        return sorted(f for f, d in self.files.items() if d == UNHASHABLE)

    def as_dict(self) -> dict[str, Any]:
        return {"digest": self.digest, "files": dict(self.files), "libraries": dict(self.libraries)}


@cache
def library_version(dist: str) -> str:
    try:
        return version(dist)
    except PackageNotFoundError:
        return "absent"


def _library_versions(imported: set[str], declared: Iterable[str]) -> dict[str, str]:
    out: dict[str, str] = {}
    for name in sorted(imported & NUMERIC_LIBRARIES.keys()):
        dists = NUMERIC_LIBRARIES[name]
        found = next(((d, v) for d in dists if (v := library_version(d)) != "absent"), (dists[0], "absent"))
        out[found[0]] = found[1]
    for dist in declared:
        out[dist] = library_version(dist)
    return dict(sorted(out.items()))


def targets_in(config: Any) -> list[str]:
    """The dotted paths of every ``_target_`` value in a config subset (hydra-instantiated classes)."""
    if isinstance(config, Mapping):
        found = [str(config["_target_"])] if isinstance(config.get("_target_"), str) else []
        return found + [t for v in config.values() for t in targets_in(v)]
    if isinstance(config, list | tuple):
        return [t for v in config for t in targets_in(v)]
    return []


def _target_modules(targets: Iterable[str]) -> list[str]:
    """``pkg.mod.Class`` -> ``pkg.mod``: every prefix is offered; prefixes that are not modules are dropped."""
    out = []
    for t in targets:
        parts = t.split(".")
        out += [".".join(parts[:i]) for i in range(1, len(parts) + 1)]
    return out


def stage_fingerprint(sd: Any, config: Mapping[str, Any] | None = None) -> CodeFingerprint:
    """The fingerprint of a ``StageDef`` run with ``config`` (its config subset, for ``_target_`` values)."""
    own = sorted({f.__module__ for f in (sd.fn, sd.setup, sd.score) if f is not None})
    targets = sorted(set(_target_modules(targets_in(dict(config or {})))) - set(own))
    return _fingerprint(tuple(own), tuple(targets), tuple(getattr(sd, "libraries", ()) or ()))


@cache
def _fingerprint(own: tuple[str, ...], targets: tuple[str, ...], declared: tuple[str, ...]) -> CodeFingerprint:
    # the package that defines a stage is first-party wherever it is installed (a plugin's package)
    modules, third = closure([*own, *targets], {m.partition(".")[0] for m in own})
    _FILES.save()
    files = {m.path: m.digest for m in sorted(modules.values(), key=lambda m: m.path) if m.digest != "namespace"}
    libraries = _library_versions(third, declared)
    payload = json.dumps({"files": files, "libraries": libraries}, sort_keys=True, separators=(",", ":"))
    return CodeFingerprint(hashlib.sha256(payload.encode()).hexdigest(), files, libraries)


def clear() -> None:
    """Forget everything computed in this process (tests, long-lived drivers after an edit)."""
    _fingerprint.cache_clear()
    _top.cache_clear()
    _find.cache_clear()
    library_version.cache_clear()
    _FILES.mem.clear()
    _FILES.loaded = False
