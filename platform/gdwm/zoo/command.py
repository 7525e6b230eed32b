"""``gdwm zoo list|show|promote|load``: the registered components of the configured MLflow store."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

from mlflow import MlflowClient
from mlflow.entities.model_registry import ModelVersion
from omegaconf import DictConfig, OmegaConf
from rich.table import Table

from gdwm.config import sqlite_path
from gdwm.errors import CommandError
from gdwm.owned import NotOurs, own_download_dir
from gdwm.redact import redact
from gdwm.term import console
from gdwm.zoo.refs import CHAMPION, ZooArgs, ZooError
from gdwm.zoo.registry import (
    TAG_KEY,
    TAG_METRIC,
    TAG_STAGE,
    TAG_VARIANT,
    aliases_of,
    download,
    flavor,
    registered,
    resolve,
    versions,
)


def _client(cfg: DictConfig) -> MlflowClient:
    uri = cfg.tracking.uri
    if (db := sqlite_path(uri)) is not None and not Path(db).is_file():
        raise ZooError(f"no MLflow store at {uri} (tracking.uri); run `gdwm run` first or set workdir=...")
    return MlflowClient(uri, registry_uri=uri)


def _args(cfg: DictConfig, need_name: bool = True) -> ZooArgs:
    args: ZooArgs = OmegaConf.to_object(cfg.args)
    if need_name and not args.name:
        raise ZooError("args.name is required, e.g. args.name=gdwm-lora (gdwm zoo list shows the names)")
    return args


def _selected(client: MlflowClient, args: ZooArgs, alias: str | None) -> ModelVersion:
    """The version ``args.version`` (``N`` or ``@ALIAS``) or ``alias`` names; neither: the newest."""
    version = args.version
    if version is not None and version.startswith("@"):
        version, alias = None, version[1:]
    if version is not None and not version.isdigit():
        raise ZooError(f"args.version={version}: a version number or @ALIAS")
    return resolve(client, args.name, int(version) if version else None, alias)


def _created(ms: int) -> str:
    return time.strftime("%Y-%m-%d %H:%M", time.localtime(ms / 1000))


def _key_metrics(client: MlflowClient, experiment: str) -> dict[str, str]:
    """Sweep name -> its table's key metric (``gdwm.key_metric``, recorded by the sweep's ``gdwm compare``)."""
    exp = client.get_experiment_by_name(experiment)
    if exp is None:
        return {}
    runs = client.search_runs([exp.experiment_id], "tags.`gdwm.kind` = 'sweep'", max_results=1000)
    return {r.data.tags["gdwm.sweep"]: r.data.tags["gdwm.key_metric"] for r in runs
            if "gdwm.key_metric" in r.data.tags and "gdwm.sweep" in r.data.tags}  # fmt: skip


def _key_value(tags: dict[str, str], keys: dict[str, str]) -> str:
    """The version's value of its sweep's key metric; without one, its ``*avg*`` metric, else its first."""
    found = {k.removeprefix(TAG_METRIC): v for k, v in tags.items() if k.startswith(TAG_METRIC)}
    key = keys.get(tags.get("gdwm.sweep", ""))
    if key is None or key not in found:
        key = next((k for k in sorted(found) if "avg" in k), next(iter(sorted(found)), None))
    return "" if key is None else f"{key}={float(found[key]):.4g}"


def zoo_list(cfg: DictConfig) -> int:
    """One row per version: variant, aliases, the sweep row that trained it and its value of the table's key metric,
    producing stage and cache key, age."""
    args, client = _args(cfg, need_name=False), _client(cfg)
    models = registered(client, args.name)
    if not models:
        console.print(f"the model zoo of {cfg.tracking.uri} is empty: training stages register their components")
        return 0
    keys = _key_metrics(client, cfg.tracking.experiment)
    t = Table(title=f"model zoo in {redact(cfg.tracking.uri)}", header_style="bold")
    for col in ("name", "version", "variant", "aliases", "row", "key metric", "stage", "cache key", "created"):
        t.add_column(col, justify="right" if col == "version" else "left")
    for model in models:
        aliases = aliases_of(model)
        for mv in versions(client, model.name):
            tags = mv.tags
            row = tags.get("gdwm.row", "")
            t.add_row(
                model.name,
                str(mv.version),
                tags.get(TAG_VARIANT, ""),
                ", ".join(aliases.get(int(mv.version), [])),
                f"{tags['gdwm.sweep']}/{row}" if row and "gdwm.sweep" in tags else row,
                _key_value(tags, keys),
                tags.get(TAG_STAGE, ""),
                tags.get(TAG_KEY, "")[:12],
                _created(mv.creation_timestamp),
            )
    console.print(t)
    return 0


def zoo_show(cfg: DictConfig) -> int:
    """Every tag of one version, its source, run and files."""
    args, client = _args(cfg), _client(cfg)
    mv = _selected(client, args, args.alias)
    aliases = aliases_of(client.get_registered_model(mv.name)).get(int(mv.version), [])
    fl = flavor(cfg.tracking.uri, mv.name, int(mv.version))
    t = Table(title=f"{mv.name} version {mv.version}", show_header=False)
    t.add_column(style="bold")
    t.add_column(overflow="fold")
    rows = [("aliases", ", ".join(aliases) or "-"), ("created", _created(mv.creation_timestamp))]
    rows += [("source", mv.source), ("run", mv.run_id or "-"), ("status", mv.status)]
    rows += [*sorted(mv.tags.items()), ("files", "\n".join(fl["files"]))]
    for k, v in rows:
        t.add_row(k, v)
    console.print(t)
    return 0


def zoo_promote(cfg: DictConfig) -> int:
    """Point ``args.alias`` (default champion) at the version ``args.version`` names."""
    args, client = _args(cfg), _client(cfg)
    if args.version is None:
        raise ZooError(f"{args.name}: args.version is required (a version number or @ALIAS, e.g. @candidate)")
    mv = _selected(client, args, None)
    alias = args.alias or CHAMPION
    before = client.get_registered_model(mv.name).aliases.get(alias)
    client.set_registered_model_alias(mv.name, alias, mv.version)
    was = f" (was version {before})" if before is not None else ""
    console.print(f"{mv.name}@{alias} -> version {mv.version}{was}")
    return 0


def zoo_load(cfg: DictConfig) -> int:
    """Download one version's files (and its MLmodel) to ``args.out``; prints the directory."""
    args, client = _args(cfg), _client(cfg)
    mv = _selected(client, args, args.alias)
    out = Path(args.out) if args.out else Path(cfg.workdir) / "zoo" / mv.name / str(mv.version)
    try:  # files land in a folder gdwm owns, never over a user's (gdwm.owned); marked once they are there
        own_download_dir(out.resolve(), create=False)
    except NotOurs as e:
        raise CommandError(str(e)) from None
    path = download(cfg.tracking.uri, mv.name, int(mv.version), out.resolve())
    own_download_dir(out.resolve())
    console.print(f"{mv.name} version {mv.version} -> {path}", soft_wrap=True)
    return 0


SUBCOMMANDS: dict[str, Callable[[DictConfig], int]] = {
    "list": zoo_list,
    "show": zoo_show,
    "promote": zoo_promote,
    "load": zoo_load,
}
