"""Zoo versions on MLflow's model registry: register a stage's component, resolve and pin references, download.

A component version is an MLflow model directory logged under ``zoo/<name>`` of the stage run that trained it: the
files plus an ``MLmodel`` whose ``gdwm`` flavor names the component, its variant and its files. Its registered
version carries the lineage as tags (``gdwm.variant``, ``gdwm.stage``, ``gdwm.cache_key``, ``gdwm.upstream.<stage>``,
``gdwm.metric.<name>``; a sweep adds ``gdwm.sweep``, ``gdwm.trial``); every new version becomes ``candidate``.

Downloads stay inside the store: a version whose files are a local directory is copied only when that directory, and
everything under it with symlinks followed, resolves inside the artifact directory of the run that registered it
(where ``register`` logs them, ``<run artifacts>/zoo/<name>``); a version registered by no run, or pointing elsewhere
(``..``, another directory, a symlink leading out), is a ZooError naming it. Remote sources are their store's business.

MLflow is imported by the functions that call it: the tag helpers are imported by every stage's Ray worker.
"""

from __future__ import annotations

import copy
import tempfile
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omegaconf import DictConfig, ListConfig

from gdwm.zoo.refs import CANDIDATE, NAME_PREFIX, Ref, ZooError, is_ref, parse_ref

if TYPE_CHECKING:
    from mlflow import MlflowClient
    from mlflow.entities.model_registry import ModelVersion, RegisteredModel

FLAVOR = "gdwm"
TAG_VARIANT, TAG_STAGE, TAG_KEY, TAG_SCENE = "gdwm.variant", "gdwm.stage", "gdwm.cache_key", "gdwm.scene"
TAG_UPSTREAM, TAG_METRIC = "gdwm.upstream.", "gdwm.metric."


def lineage_tags(
    stage: str, key: str, upstream: Mapping[str, str], metrics: Mapping[str, Any], scene: str | None = None
) -> dict[str, str]:
    """Version tags of a component a stage run produced; ``metrics``' numeric values become ``gdwm.metric.*``."""
    tags = {TAG_STAGE: stage, TAG_KEY: key, **{f"{TAG_UPSTREAM}{s}": k for s, k in upstream.items()}}
    return tags | metric_tags(metrics) | ({TAG_SCENE: scene} if scene else {})


def _numeric(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def register(
    client: MlflowClient, run_id: str, name: str, local_path: str, variant: str, tags: Mapping[str, str]
) -> int:
    """Log ``local_path`` (a file or a directory) as the MLflow model ``zoo/<name>`` of run ``run_id`` and register it
    as a new version of ``name`` with alias ``candidate``; returns the version."""
    src = Path(local_path)
    if not src.exists():
        raise ZooError(f"{name}: {src} does not exist")
    files = [p.relative_to(src).as_posix() for p in sorted(src.rglob("*")) if p.is_file()] if src.is_dir() else None
    from mlflow.exceptions import MlflowException
    from mlflow.models import Model

    artifact_path = f"zoo/{name}"
    model = Model(run_id=run_id, artifact_path=artifact_path)
    model.add_flavor(FLAVOR, component=name, variant=variant, files=[src.name] if files is None else files)
    with tempfile.TemporaryDirectory(prefix="gdwm-zoo-") as tmp:
        model.save(f"{tmp}/MLmodel")
        if src.is_dir():
            client.log_artifacts(run_id, str(src), artifact_path)
        else:
            client.log_artifact(run_id, str(src), artifact_path)
        client.log_artifact(run_id, f"{tmp}/MLmodel", artifact_path)
    try:
        client.create_registered_model(name, description=f"gdwm model zoo component {name}")
    except MlflowException as e:
        if e.error_code != "RESOURCE_ALREADY_EXISTS":
            raise
    source = f"{client.get_run(run_id).info.artifact_uri}/{artifact_path}"
    all_tags = {**tags, TAG_VARIANT: variant}
    mv = client.create_model_version(name, source, run_id, tags={k: str(v) for k, v in all_tags.items()})
    client.set_registered_model_alias(name, CANDIDATE, mv.version)
    return int(mv.version)


def registered(client: MlflowClient, name: str | None = None) -> list[RegisteredModel]:
    """The zoo's registered models (``gdwm-*``), or just ``name``, by name."""
    if name is not None:
        return [_model(client, name)]
    return sorted(client.search_registered_models(f"name LIKE '{NAME_PREFIX}%'"), key=lambda m: m.name)


def versions(client: MlflowClient, name: str) -> list[ModelVersion]:
    """Every version of ``name``, newest first."""
    return sorted(client.search_model_versions(f"name = '{name}'"), key=lambda v: -int(v.version))


def _model(client: MlflowClient, name: str) -> RegisteredModel:
    from mlflow.exceptions import MlflowException

    try:
        return client.get_registered_model(name)
    except MlflowException as e:
        if e.error_code != "RESOURCE_DOES_NOT_EXIST":
            raise
    known = ", ".join(m.name for m in registered(client)) or "none yet"
    raise ZooError(f"no registered model '{name}' in the zoo (registered: {known})")


def aliases_of(model: RegisteredModel) -> dict[int, list[str]]:
    """Version -> its aliases."""
    out: dict[int, list[str]] = {}
    for alias, v in sorted(model.aliases.items()):
        out.setdefault(int(v), []).append(alias)
    return out


def resolve(client: MlflowClient, name: str, version: int | None = None, alias: str | None = None) -> ModelVersion:
    """One version of ``name``: by number, else by alias, else the newest. A missing one is a ZooError naming it."""
    model = _model(client, name)
    if version is None and alias is not None:
        if alias not in model.aliases:
            have = ", ".join(f"{a} -> {v}" for a, v in sorted(model.aliases.items())) or "none"
            raise ZooError(f"model '{name}' has no alias '{alias}' (aliases: {have})")
        version = int(model.aliases[alias])
    found = versions(client, name)
    if version is None and found:
        return found[0]
    match = [v for v in found if int(v.version) == version]
    if not match:
        have = ", ".join(str(v.version) for v in reversed(found)) or "none"
        raise ZooError(f"model '{name}' has no version {version} (versions: {have})")
    return match[0]


def pin_references(cfg: DictConfig, tracking_uri: str, subtrees: Iterable[str] | None = None) -> DictConfig:
    """``cfg`` with every ``zoo:`` string value (under the dotted ``subtrees``, e.g. the config the stages about to
    run declare; None: anywhere) pinned to ``zoo:NAME/VERSION``, so cache keys planned from it name exact versions
    and an alias that moves later gives new keys. A copy; ``cfg`` itself when it holds no reference. A reference to
    nothing is a ZooError naming the config key and the reference."""
    if next(_references(cfg, subtrees), None) is None:
        return cfg
    from mlflow import MlflowClient

    client = MlflowClient(tracking_uri, registry_uri=tracking_uri)
    pinned = copy.deepcopy(cfg)
    for node, k, key, text in list(_references(pinned, subtrees)):
        try:
            ref = parse_ref(text)
            node[k] = str(Ref(ref.name, int(resolve(client, ref.name, ref.version, ref.alias).version)))
        except ZooError as e:
            raise ZooError(f"{key}={text}: {e}") from None
    return pinned


def _references(
    node: DictConfig | ListConfig, subtrees: Iterable[str] | None, prefix: str = ""
) -> Iterator[tuple[Any, Any, str, str]]:
    """``(container, key, dotted key, value)`` of every ``zoo:`` string under ``node`` (and ``subtrees``)."""
    roots = None if subtrees is None else tuple(subtrees)
    items = node.items() if isinstance(node, DictConfig) else enumerate(node)
    for k, v in items:
        key = f"{prefix}[{k}]" if isinstance(node, ListConfig) else f"{prefix}.{k}" if prefix else str(k)
        if isinstance(v, DictConfig | ListConfig):
            yield from _references(v, roots, key)
        elif is_ref(v) and (roots is None or any(key == r or key.startswith((f"{r}.", f"{r}[")) for r in roots)):
            yield node, k, key, v


def download(tracking_uri: str, name: str, version: int, dst: Path) -> Path:
    """The files of version ``version`` of ``name`` in ``dst`` (with the version's ``MLmodel``)."""
    return Path(_fetch(tracking_uri, name, version, "", dst))


def flavor(tracking_uri: str, name: str, version: int) -> dict:
    """The ``gdwm`` flavor of a version's ``MLmodel``: component, variant, files."""
    from mlflow.models import Model

    with tempfile.TemporaryDirectory(prefix="gdwm-zoo-") as tmp:
        return Model.load(_fetch(tracking_uri, name, version, "MLmodel", Path(tmp))).flavors[FLAVOR]


def _fetch(tracking_uri: str, name: str, version: int, path: str, dst: Path) -> str:
    # Not models:/ URIs: MLflow resolves those against the process-global registry, not this store.
    from mlflow import MlflowClient
    from mlflow.store.artifact.artifact_repository_registry import get_artifact_repository

    client = MlflowClient(tracking_uri, registry_uri=tracking_uri)
    source = client.get_model_version_download_uri(name, str(version))
    repo = get_artifact_repository(source, tracking_uri=tracking_uri)
    check_contained(client, name, version, source, tracking_uri)
    dst.mkdir(parents=True, exist_ok=True)
    return repo.download_artifacts(path, dst_path=str(dst))


def check_contained(client: MlflowClient, name: str, version: int, source: str, tracking_uri: str) -> None:
    """A ZooError naming the version and the offending path unless a local ``source`` (and all under it, symlinks
    followed) lies inside the artifact directory of the run that registered the version (see the module doc)."""
    local = _local_dir(source, tracking_uri)
    if local is None:
        return
    run_id = client.get_model_version(name, str(version)).run_id
    root = _local_dir(client.get_run(run_id).info.artifact_uri, tracking_uri) if run_id else None
    where = f"{name} version {version}: source {source}"
    if root is None:
        raise ZooError(f"{where} is a local directory but no run with local artifacts registered it; refusing it")
    base = root.resolve()
    hit = _outside(local, base, set())
    if hit is not None:
        raise ZooError(
            f"{where}: {hit[0]} leads outside the artifact directory {base} of its run {run_id} (to {hit[1]}); "
            "refusing to copy it"
        )


def _local_dir(uri: str, tracking_uri: str) -> Path | None:
    """The local directory an artifact URI stands for (``runs:/`` and ``models:/`` followed); None when remote."""
    from mlflow.store.artifact.artifact_repository_registry import get_artifact_repository
    from mlflow.store.artifact.local_artifact_repo import LocalArtifactRepository

    repo = get_artifact_repository(uri, tracking_uri=tracking_uri)
    while getattr(repo, "repo", None) is not None:
        repo = repo.repo
    return Path(repo.artifact_dir) if isinstance(repo, LocalArtifactRepository) else None


def _outside(path: Path, base: Path, seen: set[Path]) -> tuple[Path, Path] | None:
    """``(entry, where it resolves)`` of the first entry at or under ``path``, symlinks followed, outside ``base``."""
    real = path.resolve()
    if not real.is_relative_to(base):
        return path, real
    if real.is_dir() and real not in seen:
        seen.add(real)
        for child in sorted(path.iterdir()):
            if (hit := _outside(child, base, seen)) is not None:
                return hit
    return None


def tag_versions(client: MlflowClient, cache_keys: Iterable[str], tags: Mapping[str, Any]) -> list[tuple[str, int]]:
    """Add ``tags`` to every version registered by the stage runs with these cache keys (a sweep marks the versions
    a trial used: ``gdwm.sweep``, ``gdwm.trial``, ``gdwm.metric.<name>``); returns the ``(name, version)`` tagged."""
    done = []
    for key in sorted(set(cache_keys)):
        for mv in client.search_model_versions(f"tags.`{TAG_KEY}` = '{key}'"):
            for k, v in tags.items():
                client.set_model_version_tag(mv.name, mv.version, k, str(v))
            done.append((mv.name, int(mv.version)))
    return sorted(done)


def tag_run_versions(client: MlflowClient, run_ids: Iterable[str], tags: Mapping[str, Any]) -> list[tuple[str, int]]:
    """Add ``tags`` to every version the runs ``run_ids`` registered (the stage runs a sweep's trial used): one search
    per 100 runs, so a store with no zoo pays one query a trial; returns the ``(name, version)`` tagged."""
    ids = sorted(set(run_ids))
    done = []
    for start in range(0, len(ids), 100):
        listed = ", ".join(f"'{i}'" for i in ids[start : start + 100])
        for mv in client.search_model_versions(f"run_id IN ({listed})"):
            for k, v in tags.items():
                client.set_model_version_tag(mv.name, mv.version, k, str(v))
            done.append((mv.name, int(mv.version)))
    return sorted(done)


def metric_tags(metrics: Mapping[str, Any]) -> dict[str, str]:
    """``{"qa/avg": 41.2}`` -> ``{"gdwm.metric.qa/avg": "41.2"}`` (numeric values only)."""
    return {f"{TAG_METRIC}{k}": str(v) for k, v in metrics.items() if _numeric(v)}
