"""``gdwm reproduce RUN_ID [workdir=DIR]``: run a recorded trial, row, ``gdwm run`` or sweep again from scratch, in a
fresh workdir (its own cache and MLflow store), from the config each trial recorded, then say per metric and per
cache entry whether it came out equal, and what differs between the environment it was recorded in and this one.

What a launch records makes this possible (``gdwm.environment.runs``): every trial's resolved config
(``config.yaml``), the cache entries its results came from (``cache_keys.json``), its metrics, and the environment
(``environment/<digest>.json`` on the launch's run). A recorded config is composed again against today's schemas:
the dataset's schema is chosen by its recorded name, every recorded value is set over it, and a recorded key that no
setting has any more (removed since) refuses the reproduction, naming the run and the key (exit 2). Settings new
since the recording keep their defaults, and the report lists them. Paths under the recorded workdir move to the
fresh one; the cache and the store are always the fresh workdir's; data outside the workdir is read where it is.

Exit codes: 0 reproduced (every metric and entry equal), 1 not reproduced (the report says what differs) or a stage
failed, 2 bad input (unknown run, a run of another store, a config that no longer composes) before anything runs.
"""

from __future__ import annotations

import json
import math
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf, open_dict

from gdwm.fromenv import unshown


class ReproduceError(Exception):
    """Bad input, found before anything runs (exit 2): the message names the run and the key."""


REPORT = "reproduce.json"
"""The report, in the fresh workdir and on the reproduction's run."""
NOT_METRICS = ("stages_run",)
"""Metrics a ``gdwm run``'s run keeps besides its evaluation's."""


# ---- the recorded side ---------------------------------------------------------------------------------------------
@dataclass
class Recorded:
    """One recorded trial."""

    run_id: str
    label: str
    seed: int
    status: str
    """MLflow's: FINISHED, or FAILED for a trial whose stage failed (its reproduction is expected to fail too)."""
    metrics: dict[str, float]
    config: dict[str, Any]
    """Its resolved config (``config.yaml``)."""
    entries: dict[str, list[str]]
    """Stage -> the cache keys its results came from (``cache_keys.json``; per scene for per-scene stages)."""
    environment: dict[str, Any] | None


def store_uri(cfg: DictConfig, argv: list[str]) -> str:
    """The store the run is looked up in (``ReproduceArgs.store``)."""
    from gdwm.config import load_config

    given = cfg.args.store
    if given:
        return (
            given if "://" in given or given.startswith("sqlite:") else f"sqlite:///{Path(given).resolve()}/mlflow.db"
        )
    if not any(a.startswith("workdir=") for a in argv):
        return cfg.tracking.uri
    rest = [a for a in argv if not a.startswith(("workdir=", "--")) and "=" in a]
    return load_config(["args=reproduce", *rest]).tracking.uri


def open_store(uri: str, cfg: DictConfig):
    from gdwm.config import sqlite_path
    from gdwm.tracking import TrackingBackend

    db = sqlite_path(uri)
    if db is not None and not Path(db).is_file():
        raise ReproduceError(f"no MLflow store at {db}: name the run's store with args.store=WORKDIR|URI")
    return TrackingBackend(uri, cfg.tracking.experiment, None)


def find_run(backend, ref: str):
    """The run ``ref`` names in the store (its id, or a unique prefix of >= 8 characters)."""
    from mlflow.exceptions import MlflowException

    where = f"store {backend.uri}"
    try:
        return backend.client.get_run(ref)
    except MlflowException:
        pass
    if len(ref) >= 8 and all(c in "0123456789abcdef" for c in ref):
        exps = [e.experiment_id for e in backend.client.search_experiments()]
        found = backend.client.search_runs(exps, f"attributes.run_id LIKE '{ref}%'", max_results=3)
        if len(found) == 1:
            return found[0]
        if len(found) > 1:
            raise ReproduceError(f"run '{ref}' is ambiguous in {where}: "
                                 f"{', '.join(r.info.run_id for r in found)}; give more of the id")  # fmt: skip
    raise ReproduceError(f"no run '{ref}' in {where}: a run of another store? name its store with "
                         "args.store=WORKDIR (or a tracking URI)")  # fmt: skip


def _children(backend, run, kind: str) -> list:
    return [
        r
        for r in backend.client.search_runs(
            [run.info.experiment_id], f"tags.`mlflow.parentRunId` = '{run.info.run_id}'", max_results=10000
        )
        if r.data.tags.get("gdwm.kind") == kind
    ]


def trial_runs(backend, run) -> list:
    """The trial runs ``run`` stands for: itself (a trial, a one-seed ``gdwm run``), a row's or a multi-seed run's
    trials, or every trial of a sweep's rows (in table order)."""
    kind = run.data.tags.get("gdwm.kind")
    if kind == "trial":
        return [run]
    if kind in ("row", "run"):
        return sorted(_children(backend, run, "trial"), key=lambda r: int(r.data.tags.get("gdwm.seed", 0))) or [run]
    if kind == "sweep":
        rows = sorted(_children(backend, run, "row"), key=lambda r: int(r.data.tags.get("gdwm.trial_index", 0)))
        return [t for row in rows for t in trial_runs(backend, row)] + _children(backend, run, "trial")
    what = f"a {kind} run" if kind else "not a run gdwm launched"
    parent = run.data.tags.get("mlflow.parentRunId")
    hint = f"; its launch is run {parent}" if kind == "stage" and parent else ""
    raise ReproduceError(f"run {run.info.run_id} is {what}: reproduce a trial, a row, a gdwm run or a sweep{hint}")


def recorded(backend, run) -> Recorded:
    """A trial run's config, entries, metrics and environment, as recorded."""
    from gdwm.cache import CACHE_KEYS
    from gdwm.environment.runs import CONFIG_ARTIFACT, Records

    tags = dict(run.data.tags)
    label = tags.get("gdwm.row") or run.info.run_name or run.info.run_id[:12]
    with tempfile.TemporaryDirectory(prefix="gdwm-reproduce-") as tmp:
        try:
            config = OmegaConf.to_container(OmegaConf.load(_download(backend, run.info.run_id, CONFIG_ARTIFACT, tmp)))
        except FileNotFoundError:
            raise ReproduceError(
                f"run {run.info.run_id} (trial '{label}') recorded no {CONFIG_ARTIFACT}: it ran on a gdwm from before "
                "configs were recorded, so there is nothing to run again"
            ) from None
        try:
            entries = json.loads(Path(_download(backend, run.info.run_id, CACHE_KEYS, tmp)).read_text())
        except FileNotFoundError:
            entries = {}  # a failed trial records none
    return Recorded(
        run.info.run_id, label, int(tags.get("gdwm.seed", config.get("seed", 0))), run.info.status,
        {k: v for k, v in run.data.metrics.items() if k not in NOT_METRICS}, config, entries,
        Records(backend.client).of(tags),
    )  # fmt: skip


def _download(backend, run_id: str, path: str, tmp: str) -> str:
    from mlflow.exceptions import MlflowException

    try:
        return backend.client.download_artifacts(run_id, path, tmp)
    except (MlflowException, OSError) as e:
        raise FileNotFoundError(path) from e


# ---- the config, composed again ----------------------------------------------------------------------------------
def moved(value: Any, old: str, new: str) -> Any:
    """``value`` with the recorded workdir ``old`` replaced by ``new`` in every string that holds it as a path."""
    if isinstance(value, dict):
        return {k: moved(v, old, new) for k, v in value.items()}
    if isinstance(value, list):
        return [moved(v, old, new) for v in value]
    if isinstance(value, str) and old and (value == old or f"{old}/" in value):
        return value.replace(old, new)
    return value


def overlay(node: DictConfig, values: dict[str, Any], path: str = "") -> list[str]:
    """Set every recorded value over ``node`` (today's composed config). A schema's node refuses a key it has no
    field for (``ReproduceError`` naming it: removed since) and keeps fields the recording lacks (new since:
    returned); a free-form mapping (a pipeline's stages, a plugin's stage config) becomes the recorded one exactly."""
    new: list[str] = []
    schema = OmegaConf.get_type(node) not in (dict, None)
    for key, value in values.items():
        full = f"{path}{key}"
        if key not in node:
            if schema:
                raise ReproduceError(f"'{full}' is no setting any more (removed since the run was recorded?)")
            with open_dict(node):
                node[key] = value
        elif isinstance(value, dict) and isinstance(node[key], DictConfig):
            new += overlay(node[key], value, f"{full}.")
        else:
            try:
                node[key] = value
            except Exception as e:  # OmegaConf's validation: a type or choice that changed since
                raise ReproduceError(f"'{full}': the recorded value {value!r} is not valid any more ({e})") from e
    stale = [k for k in node if k not in values]
    if schema:
        new += [f"{path}{k}" for k in stale]
    else:
        with open_dict(node):
            for k in stale:
                del node[k]
    return new


def rebuild(rec: Recorded, workdir: Path) -> tuple[DictConfig, list[str]]:
    """The trial's config for a run in ``workdir``: composed today (the dataset's schema picked by its recorded
    name), every recorded value set over it, the workdir's paths moved, the cache and store the fresh workdir's."""
    from gdwm.config import ConfigError, env_sources, group_options, load_config

    launch = (rec.environment or {}).get("launch", {})
    old = launch.get("workdir") or str(Path(rec.config.get("workdir", "")).resolve())
    new = str(workdir)
    values = moved(rec.config, old, new)
    values["workdir"] = new
    values.setdefault("cache", {})["uri"] = f"{new}/cache"
    values["tracking"] = {**values.get("tracking", {}), "name": "sqlite", "uri": f"sqlite:///{new}/mlflow.db",
                          "artifact_location": f"{new}/mlartifacts", "single_writer": True}  # fmt: skip
    data = (values.get("data") or {}).get("name")
    choices = [f"data={data}"] if data in group_options("data") else []
    try:
        cfg = load_config([*choices, f"workdir={new}"])
    except ConfigError as e:
        raise ReproduceError(f"run {rec.run_id}: today's config does not compose with data={data}: {e}") from e
    try:
        fresh = overlay(cfg, unshown(values))
    except ReproduceError as e:
        raise ReproduceError(
            f"run {rec.run_id} (trial '{rec.label}'): its recorded config no longer composes: {e}"
        ) from None
    if "from_env" in cfg:  # the recorded <env:NAME> values read the environment again: secrets, as load_config says
        cfg.from_env = env_sources(cfg)
    return cfg, [k for k in fresh if not k.startswith(("args.", "hydra."))]


# ---- comparing -----------------------------------------------------------------------------------------------------
def metric_rows(then: dict[str, float], now: dict[str, float]) -> list[tuple[str, str, str, str]]:
    """(metric, recorded, reproduced, verdict) for every metric of either side; ``equal`` means bit-identical."""
    rows = []
    for m in sorted(then.keys() | now.keys()):
        a, b = then.get(m), now.get(m)
        if a is None or b is None:
            verdict = "not recorded" if a is None else "missing now"
        elif a == b or (math.isnan(a) and math.isnan(b)):
            verdict = "equal"
        else:
            verdict = f"differs by {b - a:+.6g}" + (f" ({(b - a) / abs(a):+.2%})" if a else "")
        rows.append((m, _num(a), _num(b), verdict))
    return rows


def _num(v: float | None) -> str:
    return "–" if v is None else f"{v:.10g}"


def _manifests(cache, stage: str, keys: list[str]) -> dict[str | None, Any]:
    """scene (None for a whole-stage entry) -> manifest, for the keys still in ``cache``; a missing key -> its key."""
    out: dict[str | None, Any] = {}
    for key in keys:
        m = cache.lookup(stage, key, verify=False, use=False)
        out[m.scene if m is not None else f"?{key}"] = m if m is not None else key
    return out


def why_keys_differ(a, b) -> str:
    """What made two entries of one stage get different keys: library versions, code, config, upstream, data."""
    why = []
    la, lb = (a.code or {}).get("libraries", {}), (b.code or {}).get("libraries", {})
    why += [f"library {n} {la.get(n, 'absent')} -> {lb.get(n, 'absent')}" for n in sorted(la.keys() | lb.keys())
            if la.get(n) != lb.get(n)]  # fmt: skip
    fa, fb = (a.code or {}).get("files", {}), (b.code or {}).get("files", {})
    if changed := sorted(f for f in fa.keys() | fb.keys() if fa.get(f) != fb.get(f)):
        why.append(f"code: {', '.join(changed[:3])}" + (f" and {len(changed) - 3} more" if len(changed) > 3 else ""))
    if a.config != b.config:
        why.append("config")
    if a.upstream != b.upstream:
        why.append(f"upstream: {', '.join(sorted(k for k in a.upstream if a.upstream.get(k) != b.upstream.get(k)))}")
    if a.data_fingerprint != b.data_fingerprint:
        why.append("data")
    if a.version != b.version:
        why.append(f"version {a.version} -> {b.version}")
    return "; ".join(why) or "unknown"


def entry_rows(old_cache, new_cache, then: dict[str, list[str]], now: dict[str, list[str]]) -> list[tuple]:
    """(stage, scene, recorded key, reproduced key, verdict) per cache entry: ``equal`` (the same key and the same
    bytes, every file's sha256), ``equal bytes`` under another key (with why the key moved: code, library, config,
    upstream), or which files differ."""
    rows = []
    for stage in list(dict.fromkeys([*then, *now])):
        a, b = _manifests(old_cache, stage, then.get(stage, [])), _manifests(new_cache, stage, now.get(stage, []))
        for scene in sorted(a.keys() | b.keys(), key=str):
            x, y = a.get(scene), b.get(scene)
            kx = x if isinstance(x, str) else x.key if x else ""
            ky = y if isinstance(y, str) else y.key if y else ""
            if x is None or y is None:
                verdict = "not recorded" if x is None else "not reproduced"
            elif isinstance(x, str):
                verdict = ("same key" if kx == ky else "other key") + "; the recorded entry is gone from its cache"
            else:
                files_a = {f.path: f.sha256 for f in x.files}
                files_b = {f.path: f.sha256 for f in y.files}
                differ = sorted(p for p in files_a.keys() | files_b.keys() if files_a.get(p) != files_b.get(p))
                n = f"{len(files_a)} file{'s' * (len(files_a) != 1)}"
                if not differ:  # the bytes are what reproduces; a key moves with any code or library edit
                    verdict = f"equal ({n})" if kx == ky else f"equal bytes ({n}); key differs: {why_keys_differ(x, y)}"
                else:
                    key = "same key" if kx == ky else f"key differs: {why_keys_differ(x, y)}"
                    verdict = f"bytes differ ({', '.join(differ[:3])}); {key}"
            shown = scene if isinstance(scene, str) and not scene.startswith("?") else "-"
            rows.append((stage, shown, kx[:12], ky[:12], verdict))
    return rows


# ---- the command -------------------------------------------------------------------------------------------------
def fresh_workdir(cfg: DictConfig, argv: list[str], store: str, run_id: str) -> Path:
    """``workdir=DIR`` if given (absent or empty), else ``<the store's workdir>/reproduce/<run id>[-N]``."""
    from gdwm.config import sqlite_path

    if any(a.startswith("workdir=") for a in argv):
        wd = Path(cfg.workdir).resolve()
        if wd.exists() and any(wd.iterdir()):
            raise ReproduceError(f"workdir={cfg.workdir} is not empty: a reproduction runs from scratch in a fresh "
                                 "workdir; name an absent or empty one")  # fmt: skip
        return wd
    db = sqlite_path(store)
    base = (Path(db).parent if db else Path("gdwm-reproduce").resolve()) / "reproduce" / run_id[:12]
    wd, n = base, 1
    while wd.exists():
        n += 1
        wd = base.with_name(f"{base.name}-{n}")
    return wd


def reproduce(cfg: DictConfig, argv: list[str]) -> int:
    from gdwm.compare.samples import quiet_downloads
    from gdwm.term import console

    ref = cfg.args.run
    if not ref:
        raise ReproduceError("name the run: gdwm reproduce RUN_ID [workdir=DIR]")
    uri = store_uri(cfg, argv)
    backend = open_store(uri, cfg)
    run = find_run(backend, str(ref))
    with quiet_downloads():
        trials = [recorded(backend, t) for t in trial_runs(backend, run)]
    if not trials:
        raise ReproduceError(f"run {run.info.run_id} has no trials to reproduce")
    workdir = fresh_workdir(cfg, argv, uri, run.info.run_id)
    configs = [rebuild(t, workdir) for t in trials]

    names = ", ".join(f"'{t.label}' seed {t.seed}" for t in trials)
    console.print(f"reproducing {run.data.tags.get('gdwm.kind')} {run.info.run_id}: {names}", markup=False,
                  soft_wrap=True)  # fmt: skip
    console.print(f"  recorded in {uri}; running again in the fresh workdir {workdir}", markup=False, soft_wrap=True)
    _warn_code(trials)
    new_keys = sorted({k for _, keys in configs for k in keys})
    if new_keys:
        console.print(f"settings new since the recording (today's defaults): {', '.join(new_keys)}", markup=False,
                      soft_wrap=True)  # fmt: skip

    summary = _launch(run, trials, [c for c, _ in configs])
    with quiet_downloads():
        return _report(backend, run, trials, summary, configs[0][0], workdir)


def _warn_code(trials: list[Recorded]) -> None:
    from gdwm.environment.record import commit_tag, environment
    from gdwm.term import err_console

    now = commit_tag(environment())
    for tag in dict.fromkeys(commit_tag(t.environment) for t in trials if t.environment):
        if "+dirty" in tag:
            err_console.print(f"gdwm reproduce: the run was recorded by a dirty tree ({tag}: commit {tag[:12]} plus "
                              "uncommitted changes, hashed); the code it ran is in no commit, so this reproduction "
                              f"runs today's tree ({now})", markup=False)  # fmt: skip
        elif tag != now:
            err_console.print(f"gdwm reproduce: the run was recorded at {tag}; today's tree is {now}", markup=False)
    if any(t.environment is None for t in trials):
        err_console.print("gdwm reproduce: the run recorded no environment (a gdwm from before environments were "
                          "recorded): differences in it cannot be named", markup=False)  # fmt: skip


def _launch(run, trials: list[Recorded], configs: list[DictConfig]):
    """Every recorded trial as one launch (a sweep named after the run in the fresh store): one row per recorded
    row, one trial per seed, shared stages run once."""
    from gdwm.config import SweepConfig, SweepRow
    from gdwm.dag import DagError
    from gdwm.plan import PlanError, Row, Trial, compose
    from gdwm.runner import Layout, launch
    from gdwm.zoo.refs import ZooError

    rows: dict[str, Row] = {}
    planned: list[Trial] = []
    for rec, cfg in zip(trials, configs, strict=True):
        row = rows.setdefault(rec.label, Row(len(rows), rec.label, {}, [], []))
        row.seeds.append(rec.seed)
        t = Trial(row, rec.seed)
        try:
            compose([t], None, f"reproduce {run.info.run_id}", cfg)
        except (PlanError, DagError, ZooError) as e:
            raise ReproduceError(
                f"run {rec.run_id} (trial '{rec.label}'): its recorded config no longer plans: {e}"
            ) from e
        planned.append(t)
    name = f"reproduce-{run.info.run_id[:12]}"
    sweep = SweepConfig(name=name, rows=[SweepRow(label=r.label, factors={}, overrides=[]) for r in rows.values()])
    return launch(configs[0], list(rows.values()), planned, Layout(sweep, f"sweep:{name}", planned[0].pipe.name))


def _report(backend, run, trials: list[Recorded], summary, cfg: DictConfig, workdir: Path) -> int:
    from rich.table import Table

    from gdwm.cache import Cache
    from gdwm.environment.differences import differences
    from gdwm.environment.record import commit_tag
    from gdwm.environment.record import summary as env_summary
    from gdwm.environment.runs import Records
    from gdwm.runner import entry_keys
    from gdwm.term import console
    from gdwm.tracking import TrackingBackend

    fresh = TrackingBackend(cfg.tracking.uri, cfg.tracking.experiment, cfg.tracking.artifact_location)
    now_env = Records(fresh.client).of(fresh.client.get_run(summary.parent_run_id).data.tags)
    new_cache = Cache(cfg.cache.uri)
    report: dict[str, Any] = {"run": run.info.run_id, "reproduction": summary.parent_run_id, "trials": []}
    differs = 0
    for rec, res in zip(trials, summary.trials, strict=True):
        old_cache = Cache(rec.config["cache"]["uri"])
        m_rows = metric_rows(rec.metrics, res.metrics) if res.ok else []
        e_rows = entry_rows(old_cache, new_cache, rec.entries, entry_keys(res.results)) if res.ok else []
        # gdwm's own code is said once before the start (_warn_code) and is in every entry's key: not repeated here
        env = differences(rec.environment, now_env, code=False) if rec.environment and now_env else None
        title = f"'{rec.label}' seed {rec.seed} (run {rec.run_id[:12]} -> {res.trial.run_id[:12]})"
        if res.ok != (rec.status == "FINISHED"):
            now = "finished" if res.ok else f"failed: {'; '.join(res.failed.values()) or 'blocked'}"
            console.print(f"{title}: recorded {rec.status}, the reproduction {now}", markup=False, soft_wrap=True)
            differs += 1
        console.print(title, markup=False, soft_wrap=True)
        table = Table(header_style="bold")
        for col in ("metric", "recorded", "reproduced", "verdict"):
            table.add_column(col)
        for r in m_rows:
            table.add_row(*r)
        console.print(table)
        table = Table(header_style="bold")
        for col in ("stage", "scene", "recorded key", "reproduced key", "verdict"):
            table.add_column(col)
        for r in e_rows:
            table.add_row(*r)
        console.print(table)
        if env is None:
            console.print("environment: not recorded for the run; cannot say what differs", markup=False)
        elif env:
            console.print("environment differences (recorded -> now):\n  " + "\n  ".join(env), markup=False)
        else:
            console.print(f"environment: the same ({now_env['digest']}: {env_summary(now_env)})", markup=False,
                          soft_wrap=True)  # fmt: skip
        bad_m = [r for r in m_rows if r[3] != "equal"]
        bad_e = [r for r in e_rows if not r[4].startswith("equal")]  # equal bytes under another key reproduce
        differs += bool(bad_m or bad_e)
        report["trials"].append({
            "recorded": rec.run_id, "reproduced": res.trial.run_id, "label": rec.label, "seed": rec.seed,
            "metrics": [dict(zip(("metric", "recorded", "reproduced", "verdict"), r, strict=True)) for r in m_rows],
            "entries": [dict(zip(("stage", "scene", "recorded", "reproduced", "verdict"), r, strict=True))
                        for r in e_rows],
            "environment": env,
            "code": [commit_tag(x) if x else None for x in (rec.environment, now_env)],
        })  # fmt: skip
    path = workdir / REPORT
    path.write_text(json.dumps(report, indent=1))
    fresh.log_artifact(summary.parent_run_id, str(path))
    n = len(trials)
    if differs:
        console.print(f"[red]not reproduced[/red]: {differs} of {n} trial(s) differ (report: {path})",
                      soft_wrap=True)  # fmt: skip
        return 1
    console.print(f"[green]reproduced[/green]: every metric and cache entry of {n} trial(s) equal (report: {path})",
                  soft_wrap=True)  # fmt: skip
    return 0
