"""Environment records on MLflow runs: what a launch writes, and how readers find a run's record.

A launch computes its record once (``for_launch``: the driver's, or on a remote cluster a worker's, where the
numbers are computed) and ``log_launch`` writes it as the artifact ``environment/<digest>.json`` of the launch's run
(a sweep's or a ``gdwm run``'s), and tags the launch's run, rows and trials with ``gdwm.env`` (the digest),
``gdwm.env_run`` (the run holding the artifact) and ``gdwm.commit`` (``<commit>[+dirty.<diff hash>]``). Each trial
also keeps its resolved config as ``config.yaml``: what ``gdwm reproduce`` runs again.

A trial's environment is the one of the launch that computed it: a launch that only re-reads a trial from the cache
(a resumed sweep) leaves the trial's earlier record in place.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from gdwm.environment.record import commit_tag, environment
from gdwm.fromenv import recorded as as_recorded
from gdwm.redact import redact, redact_config

DIGEST_TAG = "gdwm.env"
RECORD_RUN_TAG = "gdwm.env_run"
COMMIT_TAG = "gdwm.commit"
ARTIFACT_DIR = "environment"
CONFIG_ARTIFACT = "config.yaml"
"""A trial's resolved config (credentials masked), as its stages saw it."""


def artifact(digest: str) -> str:
    return f"{ARTIFACT_DIR}/{digest}.json"


def for_launch(cfg: DictConfig) -> dict[str, Any]:
    """The environment of a launch: this process's, or on a cluster joined by address (the driver may be a laptop)
    a worker's, with the driver's digest beside it. Ray must be up."""
    if not cfg.cluster.get("address"):
        return environment()
    import ray

    from gdwm.environment.record import summary

    here = environment()
    rec = dict(ray.get(ray.remote(num_cpus=0)(environment).remote()))
    rec["driver"] = {"host": here["host"], "digest": here["digest"], "summary": summary(here)}
    return rec


def launch_facts(cfg: DictConfig) -> dict[str, Any]:
    """How the launch was started: where from, its workdir (``gdwm reproduce`` moves paths under it) and command."""
    return {"cwd": os.getcwd(), "workdir": str(Path(cfg.workdir).resolve()), "argv": [redact(a) for a in sys.argv]}


def launch_record(cfg: DictConfig) -> dict[str, Any]:
    """The launch's environment (``for_launch``) and how it was started (``launch_facts``)."""
    return for_launch(cfg) | {"launch": launch_facts(cfg)}


def record_tags(rec: Mapping[str, Any], record_run: str) -> dict[str, str]:
    """The tags that point a run at the record ``rec`` written on ``record_run``."""
    return {DIGEST_TAG: rec["digest"], RECORD_RUN_TAG: record_run, COMMIT_TAG: commit_tag(rec)}


def log_launch(tracking, cfg: DictConfig, parent: str, trials: Iterable, recorded: set[str] | None = None,
               extra: list | None = None, rec: dict[str, Any] | None = None,
               tagged: Iterable[str] = ()) -> dict[str, Any]:  # fmt: skip
    """The launch's record (``rec``, else ``launch_record``), written on the launch's run; the launch's run, and the
    rows and trials this launch computes, tagged with it (``record_tags``; a trial every stage of which is cached
    keeps an earlier record: one search of the launch's runs tells, unless the caller knows them, ``recorded``;
    ``tagged``: runs created with the tags already); each trial so recorded gets its ``config.yaml``. One write to
    the store, with the caller's ``extra`` writes (``gdwm.tracking.RunWrite``). Returns the record."""
    from gdwm.tracking.writes import RunWrite

    trials = list(trials)
    rec = rec if rec is not None else launch_record(cfg)
    tags = record_tags(rec, parent)
    writes = [RunWrite(parent, tags=tags, texts={artifact(rec["digest"]): json.dumps(rec, indent=1, sort_keys=True)})]
    if recorded is None:
        recorded = {r["run_id"] for r in _launch_runs(tracking, trials) if r["tags"].get(DIGEST_TAG)}
    tagged = {parent, *tagged}  # runs tagged so far
    for t in trials:
        if any(r.status != "cached" for r in t.plan) or t.run_id not in recorded:
            for run_id in dict.fromkeys((t.run_id, t.row.run_id)):
                if run_id not in tagged:
                    writes.append(RunWrite(run_id, tags=tags))
                    tagged.add(run_id)
            # values from the environment as <env:NAME>, never their secret (gdwm.fromenv)
            text = OmegaConf.to_yaml(OmegaConf.create(redact_config(as_recorded(t.cfg))))
            writes.append(RunWrite(t.run_id, texts={CONFIG_ARTIFACT: text}))
    tracking.write(writes + list(extra or []))
    return rec


def _launch_runs(tracking, trials: list) -> list[dict]:
    ids = sorted({x for t in trials for x in (t.run_id, t.row.run_id) if x})
    if not ids:
        return []
    found = []
    for start in range(0, len(ids), 100):  # MLflow's IN lists stay short
        chunk = ", ".join(f"'{i}'" for i in ids[start : start + 100])
        found += tracking.search_runs(f"attributes.run_id IN ({chunk})", len(ids))
    return found


# ---- reading -----------------------------------------------------------------------------------------------------
class Records:
    """Environment records read from a store, one download per digest."""

    def __init__(self, client):
        self.client = client
        self._cache: dict[str, dict | None] = {}

    def of(self, tags: dict[str, str]) -> dict[str, Any] | None:
        """The record a run's tags point to; None for a run recorded without one (an older gdwm), or whose
        record's run is gone."""
        digest, holder = tags.get(DIGEST_TAG), tags.get(RECORD_RUN_TAG)
        if not digest or not holder:
            return None
        if digest not in self._cache:
            self._cache[digest] = self._download(holder, artifact(digest))
        return self._cache[digest]

    def _download(self, run_id: str, path: str) -> dict | None:
        try:
            with tempfile.TemporaryDirectory(prefix="gdwm-env-") as tmp:
                return json.loads(Path(self.client.download_artifacts(run_id, path, tmp)).read_text())
        except Exception:  # a run deleted since, an artifact store out of reach: the record is unknown
            return None


def tag_run(backend, run_id: str, rec: dict[str, Any]) -> None:
    """Record ``rec`` on one run written directly to a backend (``gdwm regress``'s regression run)."""
    backend.log_text(run_id, json.dumps(rec, indent=1, sort_keys=True), artifact(rec["digest"]))
    backend.set_tags(run_id, {DIGEST_TAG: rec["digest"], RECORD_RUN_TAG: run_id, COMMIT_TAG: commit_tag(rec)})


# ---- what readers say ------------------------------------------------------------------------------------------
def baseline_flags(backend, base_id: str, now: dict[str, Any]) -> list[str]:
    """``gdwm regress``: a baseline recorded in another environment (or without one) is a weaker reference."""
    from gdwm.environment.differences import brief, differences

    tags = backend.client.get_run(base_id).data.tags
    base = Records(backend.client).of(tags)
    if base is None:
        return [f"baseline run {base_id[:12]} recorded no environment (an older gdwm): whether it ran in this one is "
                "unknown; re-record it with --set-baseline"]  # fmt: skip
    if base["digest"] == now["digest"]:
        return []
    return [f"baseline run {base_id[:12]} ran in another environment ({base['digest']} -> {now['digest']}: "
            f"{brief(differences(base, now, code=False))}): float rounding may move its numbers; re-record it here "
            "with --set-baseline"]  # fmt: skip


def environment_note(backend, rows: list) -> str | None:
    """``gdwm compare``'s note when a table's rows come from more than one environment (or some recorded none): which
    rows ran where, and what differs from the first row's environment; None when they all ran in one."""
    from gdwm.environment.differences import brief, differences
    from gdwm.environment.record import summary

    records = Records(backend.client)
    where: dict[str, list[str]] = {}  # digest ("" = none recorded) -> the rows (and seeds) that ran there
    for row in rows:
        trials = row.counted or row.trials
        for t in trials:
            label = row.label if len(trials) == 1 else f"{row.label} (seed {t.seed})"
            where.setdefault(t.tags.get(DIGEST_TAG, ""), []).append(label)
    recorded = [d for d in where if d]
    if len(recorded) < 2 and (not recorded or "" not in where):
        return None
    first = records.of({DIGEST_TAG: recorded[0], RECORD_RUN_TAG: _holder(rows, recorded[0])}) if recorded else None
    parts = []
    for d, labels in where.items():
        rec = records.of({DIGEST_TAG: d, RECORD_RUN_TAG: _holder(rows, d)}) if d else None
        if not d:
            parts.append(f"{', '.join(labels)}: no environment recorded (an older gdwm)")
        elif rec is None or first is None:
            parts.append(f"{', '.join(labels)}: environment {d} (its record is gone)")
        elif d == recorded[0]:
            parts.append(f"{', '.join(labels)}: environment {d} ({summary(rec)})")
        else:
            parts.append(f"{', '.join(labels)}: environment {d}, which differs from {recorded[0]} in: "
                         f"{brief(differences(first, rec, code=False))}")  # fmt: skip
    return ("Environments differ between rows (numbers may move by float rounding across CPUs and library "
            "versions): " + "; ".join(parts) + ".")  # fmt: skip


def _holder(rows: list, digest: str) -> str | None:
    return next((t.tags.get(RECORD_RUN_TAG) for r in rows for t in r.trials if t.tags.get(DIGEST_TAG) == digest), None)
