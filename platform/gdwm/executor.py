"""Stages as Ray tasks whose arguments are upstream results; per-scene stages in actor pools.

Each stage task computes its cache key from its upstream results' keys and its code fingerprint
(``RunEnv.code``, computed on the driver), returns at once on a cache hit (no MLflow run), else
runs the stage under one MLflow run (one per cache key: a killed attempt's run is reopened, never
duplicated), publishes atomically, registers the model-zoo components the stage declared
(``ctx.register``) and returns. A stage task that fails raises ``StageFailed``; Ray then never
starts its descendants.

What counts as a hit is ``cache.reuse`` (per stage, ``RunEnv.reuse``): ``same_code`` -- the entry of this very
key; ``all`` -- else the newest entry of the same config under any code (its ``base``); ``none`` -- never: the
stage recomputes, its output replaces the entry and its training checkpoints are discarded first.
"""

from __future__ import annotations

import json
import tempfile
import time
import traceback
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import ray

from gdwm.cache import Cache, Manifest, cache_key
from gdwm.determinism import stage_end, stage_start
from gdwm.errors import oom_line
from gdwm.fromenv import masked, restore
from gdwm.keylock import KeyLock
from gdwm.stage import StageContext, StageDef, UpstreamOutput
from gdwm.tracking import NewRun, RunWrite, Sink, Tracker, TrackingClient
from gdwm.tracking.params import flatten_params, relative_paths
from gdwm.zoo.registry import lineage_tags

TAG_STAGE, TAG_KEY, TAG_VERSION, TAG_SCENES = "gdwm.stage", "gdwm.cache_key", "gdwm.version", "gdwm.scenes"
TAG_CODE, TAG_CODE_RUN = "gdwm.code", "gdwm.code_run"
"""On a stage run: its code fingerprint's digest, and the run holding that fingerprint as ``code_artifact(digest)``
(the launch's run; absent on runs that hold it themselves as ``code.json``: see ``read_code_record``)."""
TAG_RECOMPUTES = "gdwm.recomputes"
"""On a stage run that recomputed a key whose earlier run had finished: that run's id."""
CODE_JSON = "code.json"
"""A stage run's own code record (runs of gdwm before launch-level records, or a stage the launch did not plan)."""


def code_artifact(digest: str) -> str:
    """Where a launch's run holds the code fingerprint of that digest (files with their hashes, libraries)."""
    return f"code/{digest}.json"


def read_code_record(client: Any, run: Any, dst: str) -> dict[str, Any] | None:
    """The code fingerprint behind a stage run (``mlflow.entities.Run``), downloaded with ``client`` into ``dst``:
    from the run ``gdwm.code_run`` names, else the run's own ``code.json``; None for a run without ``gdwm.code``."""
    digest = run.data.tags.get(TAG_CODE)
    if digest is None:
        return None
    holder = run.data.tags.get(TAG_CODE_RUN)
    path = (holder, code_artifact(digest)) if holder else (run.info.run_id, CODE_JSON)
    return json.loads(Path(client.download_artifacts(*path, dst)).read_text())


SAME_CODE, ALL, NONE = "same_code", "all", "none"
"""``cache.reuse`` modes (``gdwm.config.ReuseMode``)."""
COMPUTED, REUSED_SAME, REUSED_OTHER, REUSED_UNKNOWN = "", "same code", "other code", "unknown code"
"""``StageResult.reused``: computed now, or the entry it came from was computed by the same/other/unknown code."""


class StageFailed(Exception):
    """A stage (or some of its scenes, or its actors' ``setup``) raised; the message is one line naming the stage,
    the scenes and the error (its type and message); ``errors`` holds each full traceback."""

    def __init__(self, stage: str, errors: Mapping[str | None, str], setup: bool = False):
        self.stage = stage
        self.errors = dict(errors)
        self.setup = setup
        scenes = [s for s in self.errors if s is not None]
        where = f"stage '{stage}'" + (f" scene(s) {scenes}" if scenes else "")
        last = _last_line(next(iter(self.errors.values()))) if self.errors else ""
        super().__init__(f"{where} failed{' in setup' if setup else ''}: {last}")

    def __reduce__(self):
        return (StageFailed, (self.stage, self.errors, self.setup))


def _last_line(text: str) -> str:
    """A traceback's ``Type: message`` line (its last), for the one-line message."""
    from gdwm.errors import _last_error_line

    return _last_error_line(text) or text.strip().splitlines()[-1]


class SetupFailed(Exception):
    """A scene actor's ``setup`` raised (carried by its first ``process`` call: the stage's error, not a lost node)."""


@dataclass(frozen=True)
class RunEnv:
    """Everything a stage task needs besides its own definition; plain, picklable."""

    cache_uri: str
    data_root: str
    data_fingerprint: str
    scenes: tuple[str, ...]
    checkpoint_root: str
    sink: Sink
    """The tracking backend or its actor handle, shipped as is (both pickle); ``tracking`` calls it."""
    parent_run_id: str | None
    progress: Any
    resources: Mapping[str, Mapping[str, float]]
    on_scene_error: str = "fail"
    max_retries: int = 3
    deterministic: bool | None = None
    """``run.deterministic`` (null: on without CUDA), applied where each stage runs."""
    train_settings: Mapping[str, Any] = field(default_factory=dict)
    run_tags: Mapping[str, str] = field(default_factory=dict)
    tracking_uri: str | None = None
    """Where stages read zoo versions from (``ctx.zoo_path``); writes go through ``sink``."""
    code: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    """Stage -> its code fingerprint (``gdwm.fingerprint.CodeFingerprint.as_dict``); its digest enters the key."""
    code_recorded: frozenset[str] = frozenset()
    """The fingerprint digests ``parent_run_id`` holds as ``code_artifact(digest)`` (the launch writes each once);
    a stage run whose code is among them points there instead of holding ``code.json`` itself."""
    reuse: Mapping[str, str] = field(default_factory=dict)
    """Stage -> ``cache.reuse`` mode (default ``same_code``)."""
    verify: bool = True
    """``cache.verify``: re-hash an entry's files on every lookup (else trust a complete manifest and the sizes)."""
    env_values: Mapping[str, Any] = field(default_factory=dict)
    """Config key -> the value it took from the environment: what a stage reads where its subset records
    ``<env:NAME>`` (``gdwm.fromenv``)."""

    @property
    def tracking(self) -> TrackingClient:
        return TrackingClient(self.sink)


@dataclass(frozen=True)
class StageResult:
    stage: str
    key: str
    cached: bool
    run_id: str | None
    path: str | None = None
    """Local directory of the entry (non-per-scene stages)."""
    scenes: Mapping[str, tuple[str, str]] = field(default_factory=dict)
    """Per-scene stages: scene -> (key, local dir) of every scene that has an entry."""
    failed: Mapping[str, str] = field(default_factory=dict)
    """Per-scene stages with on_scene_error=skip: scene -> traceback of the scenes left out."""
    extra: Mapping[str, Any] = field(default_factory=dict)
    base: str = ""
    """The code-free key (per-scene stages: over the scenes' bases), what ``cache.reuse=all`` looks up."""
    bases: Mapping[str, str] = field(default_factory=dict)
    """Per-scene stages: scene -> that scene's base."""
    reused: str = COMPUTED
    """Where the output came from: ``COMPUTED`` now, or an entry of the same / other / unknown code (per-scene
    stages: the least trustworthy of their scenes')."""
    registered: bool | None = None
    """Whether its run registered zoo versions: known (False: none) for a stage this launch computed whole, None
    (perhaps) for a cache hit or a per-scene stage; a trial's zoo lineage searches only the runs that may have."""


SEED_KEY = "seed"
"""Where a seeded stage's config subset carries the trial seed (so it enters the key, manifest and params)."""


def stage_config(sd: StageDef, cfg: Any) -> dict[str, Any]:
    """The config a stage's key and run depend on: its declared subtrees (resolved, plain), plus the trial seed
    (``cfg.seed``) for a seeded stage."""
    from omegaconf import OmegaConf

    out = {k: OmegaConf.to_container(OmegaConf.select(cfg, k), resolve=True) for k in sd.config}
    if sd.seeded:
        out[SEED_KEY] = int(cfg.seed)
    # values from the environment (secrets) enter key, manifest and params as their interpolation (gdwm.fromenv)
    return masked(out, cfg.get("from_env") or {})


def code_digest(env: RunEnv, stage: str) -> str | None:
    fp = env.code.get(stage)
    return fp["digest"] if fp else None


def stage_key(sd: StageDef, subset: Mapping, upstream: Mapping[str, str], env: RunEnv, scene: str | None = None) -> str:
    """The entry's key: config subset, upstream keys, data, scene and the stage's code fingerprint."""
    return cache_key(sd.name, sd.version, dict(subset), dict(upstream), env.data_fingerprint, scene,
                     code_digest(env, sd.name))  # fmt: skip


def stage_base(sd: StageDef, subset: Mapping, upstream: Mapping[str, str], env: RunEnv, scene: str | None = None
               ) -> str:  # fmt: skip
    """The code-free key over the upstream's bases: the same config and data under any code."""
    return cache_key(sd.name, sd.version, dict(subset), dict(upstream), env.data_fingerprint, scene)


def aggregate_key(sd: StageDef, subset: Mapping, scene_keys: Mapping[str, str], env: RunEnv) -> str:
    """A per-scene stage's key as seen downstream: it changes with any scene's key or the set of scenes (given
    scene bases, the aggregate base)."""
    return cache_key(
        sd.name, sd.version, dict(subset), {f"scene:{s}": k for s, k in scene_keys.items()}, env.data_fingerprint
    )


def upstream_keys(results: tuple[StageResult, ...], scene: str | None) -> dict[str, str]:
    """Keys this stage depends on; a per-scene stage depends on the same scene of a per-scene upstream."""
    out = {}
    for r in results:
        out[r.stage] = r.scenes[scene][0] if (scene is not None and r.scenes) else r.key
    return out


def upstream_bases(results: tuple[StageResult, ...], scene: str | None) -> dict[str, str]:
    out = {}
    for r in results:
        out[r.stage] = r.bases[scene] if (scene is not None and r.bases) else r.base
    return out


def find_entry(cache: Cache, stage: str, key: str, base: str, mode: str, verify: bool = True, use: bool = True
               ) -> tuple[Manifest | None, str]:  # fmt: skip
    """The entry a stage reuses under ``mode`` and where it came from (``REUSED_*``); (None, COMPUTED) = run it."""
    if mode == NONE:
        return None, COMPUTED
    m = cache.lookup(stage, key, verify, use)
    if m is not None:
        return m, REUSED_SAME
    if mode != ALL:
        return None, COMPUTED
    m = cache.lookup_base(stage, base, verify, use)
    if m is None:
        return None, COMPUTED
    return m, REUSED_UNKNOWN if m.code is None else REUSED_OTHER


def least_trusted(how: list[str]) -> str:
    """A per-scene stage's provenance: computed if any scene ran, else the least trustworthy reuse."""
    for h in (COMPUTED, REUSED_UNKNOWN, REUSED_OTHER):
        if h in how:
            return h
    return REUSED_SAME


def _discard_checkpoints(checkpoint_root: str, stage: str, key: str) -> None:
    """A recompute (forced, or after a corrupt entry) must not resume from that key's old checkpoints."""
    from gdwm.training import discard_checkpoints

    discard_checkpoints(checkpoint_root, stage, key)


def verified(cache: Cache, checkpoint_root: str, stage: str, key: str, verify: bool = True) -> bool:
    """The entry is present and intact (``verify``: its files re-hashed); a corrupt one is moved aside with its key's
    training checkpoints."""
    if cache.lookup(stage, key, verify=verify) is not None:
        return True
    if any(k == key for _, k, _ in cache.last_invalid):
        _discard_checkpoints(checkpoint_root, stage, key)
    return False


def _lookup(cache: Cache, env: RunEnv, sd: StageDef, key: str, base: str) -> tuple[Manifest | None, str]:
    mode = env.reuse.get(sd.name, SAME_CODE)
    hit, how = find_entry(cache, sd.name, key, base, mode, env.verify)
    if hit is None and (mode == NONE or any(k == key for _, k, _ in cache.last_invalid)):
        _discard_checkpoints(env.checkpoint_root, sd.name, key)
    return hit, how


def upstream_views(results: tuple[StageResult, ...]) -> dict[str, UpstreamOutput]:
    return {
        r.stage: UpstreamOutput(
            r.stage,
            r.key,
            Path(r.path) if r.path else None,
            dict(r.extra),
            {s: Path(p) for s, (_, p) in r.scenes.items()},
        )
        for r in results
    }


def _progress(env: RunEnv, scene: str | None, state: str, message: str | None = None) -> None:
    """A worker's event (``gdwm.progress.Reporter``): an execution or scene started; a scene's outcome. The
    execution's own outcome is the driver's to report (it sees the result, a killed worker can't say)."""
    if env.progress is not None:
        env.progress.state(state, scene, message)


def _open_stage_run(env: RunEnv, sd: StageDef, key: str, subset: Mapping, tags: Mapping[str, str] | None = None) -> str:
    """The MLflow run for this key, in one call to the store (``TrackingBackend.keyed_run``): an unfinished earlier
    attempt's is reopened (a killed attempt leaves no duplicate); after a finished one (a recompute: a corrupt or
    invalidated entry, a re-run scene, a forced recompute) a new run is created, tagged ``gdwm.recomputes`` with the
    original, whose history stays as it was. A new run carries the stage's params (paths relative to the workdir,
    the checkpoint root's parent: params describe the stage, not the machine) and the code behind its key (tag
    ``gdwm.code``; the fingerprint's digest, files and libraries on the launch's run, ``gdwm.code_run``, where the
    launch recorded it, else the run's own ``code.json``: ``read_code_record``)."""
    fp = env.code.get(sd.name)
    extra, texts = dict(tags or {}), {}
    if fp is not None and fp["digest"] in env.code_recorded and env.parent_run_id:
        extra |= {TAG_CODE: fp["digest"], TAG_CODE_RUN: env.parent_run_id}  # one record per launch, not per run
    elif fp is not None:
        extra[TAG_CODE] = fp["digest"]
        texts = {CODE_JSON: json.dumps(fp, indent=1, sort_keys=True)}
    new_tags = {TAG_STAGE: sd.name, TAG_KEY: key, TAG_VERSION: sd.version, "gdwm.kind": "stage", **env.run_tags}
    params = relative_paths(flatten_params(dict(subset)), Path(env.checkpoint_root).parent)
    new = NewRun(f"{sd.name}-{key[:8]}", new_tags | extra, env.parent_run_id, params, texts)
    resumed = {"gdwm.resumed": "true"} | extra
    return env.tracking.keyed_run({TAG_KEY: key, TAG_STAGE: sd.name}, new, resumed, TAG_RECOMPUTES)


def _context(sd: StageDef, key: str, subset, env: RunEnv, results, out_dir: Path, tracker, scene=None, state=None):
    return StageContext(
        name=sd.name,
        key=key,
        config=restore(subset, env.env_values),
        out_dir=out_dir,
        upstream=upstream_views(results),
        data_root=Path(env.data_root),
        data_fingerprint=env.data_fingerprint,
        tracker=tracker,
        checkpoint_dir=Path(env.checkpoint_root) / sd.name / key,
        resources=dict(env.resources.get(sd.resources, {})),
        scene=scene,
        state=state,
        progress_sink=env.progress,
        seed=subset[SEED_KEY] if sd.seeded else None,
        deterministic=env.deterministic,
        train_settings=dict(env.train_settings),
        tracking_uri=env.tracking_uri,
    )


def _execute(sd, key, base, subset, env, results, tracker, scene=None, state=None) -> tuple[str, dict, bool]:
    """Run the stage function into a temp dir and publish it; returns (local entry dir, manifest extra, whether it
    registered zoo versions)."""
    cache = Cache(env.cache_uri)
    with tempfile.TemporaryDirectory(prefix=f"gdwm-{sd.name}-") as tmp:
        out = Path(tmp) / "out"
        out.mkdir()
        ctx = _context(sd, key, subset, env, results, out, tracker, scene, state)
        # whatever earlier tasks left in this worker's generators and thread count must not reach the output
        stage_start(ctx.seed or 0, ctx.resources.get("num_cpus", 1), env.deterministic)
        try:
            extra = sd.fn(ctx) or {}
        finally:
            stage_end()
        if not isinstance(extra, dict):
            raise TypeError(f"stage '{sd.name}' returned {type(extra).__name__}; return None or a JSON-able dict")
        tracker.flush()
        m = cache.publish(
            sd.name,
            key,
            out,
            config=dict(subset),
            upstream=upstream_keys(results, scene),
            data_fingerprint=env.data_fingerprint,
            version=sd.version,
            scene=scene,
            run_id=tracker.run_id,
            extra=extra,
            code=env.code.get(sd.name),
            base=base,
            replace=env.reuse.get(sd.name) == NONE,
        )
        ours = m.run_id == tracker.run_id  # else another attempt published this key first (and registered its own)
        if ours:
            for r in ctx.registrations:
                tags = {**lineage_tags(sd.name, key, m.upstream, m.extra, scene), **r.tags}
                env.tracking.register_component(m.run_id, r.name, str(out / r.path), r.variant, tags)
        return str(cache.materialize(m)), dict(m.extra), ours and bool(ctx.registrations)


class ScopedTracker(Tracker):
    """A per-scene view of the stage run: metric and param names get the scene as a prefix."""

    def __init__(self, sink, run_id: str, prefix: str):
        super().__init__(sink, run_id)
        self.prefix = prefix

    def __getstate__(self):
        return {**super().__getstate__(), "prefix": self.prefix}

    def __setstate__(self, state):
        self.__init__(state["sink"], state["run_id"], state["prefix"])

    def log_metrics(self, metrics, step=None):
        super().log_metrics({f"{self.prefix}{k}": v for k, v in metrics.items()}, step)

    def log_params(self, params):
        super().log_params({f"{self.prefix}{k}": v for k, v in params.items()})


@ray.remote
def run_stage(sd: StageDef, subset: dict, env: RunEnv, *results: StageResult) -> StageResult:
    """One whole-dataset stage (``per_scene=False``)."""
    cache = Cache(env.cache_uri)
    key = stage_key(sd, subset, upstream_keys(results, None), env)
    base = stage_base(sd, subset, upstream_bases(results, None), env)
    hit, how = _lookup(cache, env, sd, key, base)
    if hit is None:
        with _key_lock(cache, env, sd.name, None, key):
            hit, how = _lookup(cache, env, sd, key, base)  # another driver may have computed it while we waited
            if hit is None:
                return _compute(sd, key, base, subset, env, results)
    path = str(cache.materialize(hit))
    return StageResult(sd.name, hit.key, True, hit.run_id, path, extra=dict(hit.extra), base=base, reused=how)


def _compute(sd: StageDef, key: str, base: str, subset: dict, env: RunEnv, results) -> StageResult:
    run_id = _open_stage_run(env, sd, key, subset)
    _progress(env, None, "running")
    tracker = Tracker(env.sink, run_id)
    try:
        path, extra, registered = _execute(sd, key, base, subset, env, results, tracker)
    except Exception as e:
        tb = traceback.format_exc()
        _end_failed(env, run_id, tb)
        raise StageFailed(sd.name, {None: tb}) from e
    env.tracking.end_run(run_id, "FINISHED")
    return StageResult(sd.name, key, False, run_id, path, extra=extra, base=base, registered=registered)


def _key_lock(cache: Cache, env: RunEnv, stage: str, scene: str | None, key: str) -> KeyLock:
    """The key's lock (see ``gdwm.keylock``); waiting for another driver shows on the progress board."""

    def waiting(owner: str) -> None:
        _progress(env, scene, "running", message=f"waiting: another driver computes it ({owner})")

    return KeyLock(cache, stage, key, on_wait=waiting)


def _end_failed(env: RunEnv, run_id: str, text: str) -> None:
    env.tracking.write([RunWrite(run_id, texts={"error.txt": text}, end="FAILED")])


class SceneWorker:
    """Holds a per-scene stage's heavy state (``setup``) and processes scenes one at a time."""

    def __init__(self, sd: StageDef, subset: dict, num_cpus: float, deterministic: bool | None):
        self.sd = sd
        self.setup_error: str | None = None
        stage_start(0, num_cpus, deterministic)  # heavy state (a random projection, say) the same in every actor
        try:
            self.state = sd.setup(subset) if sd.setup is not None else None
        except Exception:
            # Kept, not raised: an actor whose constructor raises is dead, and Ray would restart and retry it as if
            # its node were lost. The stage's own error fails the stage once (process raises it).
            self.state, self.setup_error = None, traceback.format_exc()
        finally:
            stage_end()

    def process(self, scene: str, key: str, base: str, subset: dict, env: RunEnv, run_id: str, *results: StageResult):
        if self.setup_error is not None:
            raise SetupFailed(self.setup_error)
        cache = Cache(env.cache_uri)
        # A driver running another configuration may share this scene's key (same upstream, different scene set).
        with _key_lock(cache, env, self.sd.name, scene, key):
            forced = env.reuse.get(self.sd.name) == NONE
            if not forced and (hit := cache.lookup(self.sd.name, key, env.verify)) is not None:
                _progress(env, scene, "cached")
                return str(cache.materialize(hit))
            _progress(env, scene, "running")
            tracker = ScopedTracker(env.sink, run_id, f"{scene}/")
            path, _, _ = _execute(self.sd, key, base, subset, env, results, tracker, scene, self.state)
        _progress(env, scene, "done")
        return path


@ray.remote(num_cpus=0)
def run_scene_stage(sd: StageDef, subset: dict, env: RunEnv, *results: StageResult) -> StageResult:
    """A per-scene stage: cache per scene, misses go to a pool of actors that load heavy state once."""
    cache = Cache(env.cache_uri)
    upstream_failed = {s for r in results for s in r.failed}
    scenes = [s for s in env.scenes if s not in upstream_failed]
    keys = {s: stage_key(sd, subset, upstream_keys(results, s), env, scene=s) for s in scenes}
    bases = {s: stage_base(sd, subset, upstream_bases(results, s), env, scene=s) for s in scenes}
    done: dict[str, tuple[str, str]] = {}
    how: dict[str, str] = {}

    def look(todo: list[str]) -> tuple[list[str], str]:
        """The scenes of ``todo`` without an entry, and the aggregate key of the stage as of now."""
        misses = []
        for s in todo:
            hit, how[s] = _lookup(cache, env, sd, keys[s], bases[s])
            if hit is None:
                misses.append(s)
            else:
                done[s] = (hit.key, str(cache.materialize(hit)))
                _progress(env, s, "cached")
        return misses, aggregate_key(sd, subset, {s: done[s][0] if s in done else keys[s] for s in scenes}, env)

    agg_base = aggregate_key(sd, subset, bases, env)
    misses, agg = look(scenes)
    if misses:
        with _key_lock(cache, env, sd.name, None, agg):
            misses, agg = look(misses)  # another driver may have computed them while we waited
            if misses:
                return _compute_scenes(sd, subset, env, results, scenes, misses, keys, bases, done, agg)
    return StageResult(sd.name, agg, True, None, scenes=done, base=agg_base, bases=bases,
                       reused=least_trusted(list(how.values())))  # fmt: skip


def _compute_scenes(sd, subset, env: RunEnv, results, scenes, misses, keys, bases, done, agg) -> StageResult:
    upstream_failed = {s for r in results for s in r.failed}
    run_id = _open_stage_run(env, sd, agg, subset, {TAG_SCENES: ",".join(misses)})
    _progress(env, None, "running")
    try:
        errors = _run_pool(sd, subset, env, run_id, results, misses, keys, bases, done)
    except StageFailed as e:  # its actors' setup raised
        _end_failed(env, run_id, next(iter(e.errors.values())))
        raise
    for s in upstream_failed:
        _progress(env, s, "blocked")
    if errors and env.on_scene_error == "fail":
        _end_failed(env, run_id, "\n\n".join(f"== {s} ==\n{tb}" for s, tb in errors.items()))
        raise StageFailed(sd.name, errors)
    skipped = {"skipped.txt": "\n\n".join(f"== {s} ==\n{tb}" for s, tb in errors.items())} if errors else {}
    done = {s: done[s] for s in scenes if s in done}  # the dataset's scene order, not the order scenes finished in
    agg = aggregate_key(sd, subset, {s: k for s, (k, _) in done.items()}, env)
    agg_base = aggregate_key(sd, subset, {s: bases[s] for s in done}, env)
    env.tracking.write([RunWrite(run_id, texts=skipped, end="FINISHED")])
    return StageResult(sd.name, agg, False, run_id, scenes=done, failed={**errors}, base=agg_base,
                       bases={s: bases[s] for s in done})  # fmt: skip


def _run_pool(sd, subset, env: RunEnv, run_id, results, misses, keys, bases, done) -> dict[str, str]:
    """The scenes of ``misses`` on a pool of up to ``num_workers`` actors; returns scene -> traceback of those that
    failed.

    A scene goes only to an actor that is placed and idle, never to one still waiting for resources: pools of
    concurrent per-scene stages that each got part of the cluster all make progress (scenes pinned to every actor
    up front left each pool waiting on its unplaced actor while its placed one sat idle, holding the CPUs the
    others waited for). Actors no scene needs any more are released at once, placed or not."""
    res = env.resources.get(sd.resources, {})
    n = max(1, min(len(misses), int(res.get("num_workers", 1)) or 1))
    actor_cls = ray.remote(SceneWorker).options(
        num_cpus=float(res.get("num_cpus", 1)),
        num_gpus=float(res.get("num_gpus", 0)),
        max_restarts=env.max_retries,
        max_task_retries=env.max_retries,
    )
    starting: dict[ray.ObjectRef, Any] = {}  # an actor's placement (its __ray_ready__) -> the actor
    idle: list = []
    queue = list(misses)
    running: dict[ray.ObjectRef, tuple[str, Any]] = {}
    errors: dict[str, str] = {}
    lost: dict[str, int] = {}
    replaced = 0

    def new_actor() -> None:
        a = actor_cls.remote(sd, subset, float(res.get("num_cpus", 1)), env.deterministic)
        starting[a.__ray_ready__.remote()] = a

    def release(actors: list) -> None:
        for a in actors:
            ray.kill(a)

    for _ in range(n):
        new_actor()
    try:
        while queue or running:
            while queue and idle:
                s, actor = queue.pop(0), idle.pop()
                running[actor.process.remote(s, keys[s], bases[s], subset, env, run_id, *results)] = (s, actor)
            if not queue:  # the last scenes are running: what waits for them holds resources others need
                release(idle + list(starting.values()))
                idle.clear()
                starting.clear()
                if not running:
                    break
            if not starting and not running and not idle:  # every actor lost for good: start another
                new_actor()
            [ref], _ = ray.wait([*running, *starting], num_returns=1)
            if ref in starting:
                actor = starting.pop(ref)
                try:
                    ray.get(ref)
                    idle.append(actor)
                except ray.exceptions.RayActorError as e:
                    if getattr(e, "actor_init_failed", False):  # its setup raised: the stage's error, not a lost node
                        raise
                    replaced += 1  # its node was lost while it started
                    if replaced > env.max_retries * n:
                        raise StageFailed(sd.name, {None: f"the stage's actors were lost {replaced} times: {e}"}) from e
                    new_actor()
                continue
            s, actor = running.pop(ref)
            try:
                done[s] = (keys[s], ray.get(ref))
            except ray.exceptions.OutOfMemoryError as e:  # the scene's worker filled the node: not retried
                errors[s] = oom_line(e)
                _progress(env, s, "failed", message="out of memory")
            except ray.exceptions.RayTaskError as e:
                if isinstance(e.cause, SetupFailed):  # the stage's own error: every scene would fail alike
                    # the other actors' calls fail alike at once: they end before their actors are killed (a killed
                    # actor's call in flight is one Ray would retry, and says so on the console)
                    ray.wait(list(running), num_returns=len(running), timeout=30)
                    raise StageFailed(sd.name, {None: str(e.cause)}, setup=True) from None
                errors[s] = _user_traceback(e)
                _progress(env, s, "failed")
            except ray.exceptions.RayActorError as e:
                if getattr(e, "actor_init_failed", False):  # its setup raised: the stage's error, not a lost node
                    raise
                # The actor's node was lost. Ray's own task retries can run out before it marks the node dead
                # (each retry is refused at once), so the scene goes back to the queue, after a pause, up to
                # run.max_retries times; an actor that is dead for good is replaced.
                lost[s] = lost.get(s, 0) + 1
                if lost[s] > env.max_retries:
                    errors[s] = f"the scene's worker was lost {lost[s]} times: {type(e).__name__}: {e}"
                    _progress(env, s, "failed")
                else:
                    time.sleep(min(2.0 ** lost[s], 10.0))
                    queue.insert(0, s)
                if isinstance(e, ray.exceptions.ActorDiedError):
                    ray.kill(actor)
                    new_actor()
                    continue
            idle.append(actor)
    finally:
        release(idle + list(starting.values()) + [a for _, a in running.values()])
    return errors


def _user_traceback(e: ray.exceptions.RayTaskError) -> str:
    cause = e.cause if isinstance(e.cause, BaseException) else None
    if cause is not None:
        return "".join(traceback.format_exception(cause))
    return str(e)


def task_options(sd: StageDef, env: RunEnv) -> dict:
    """Ray options of a stage's coordinating task; resources come from the cluster config only."""
    res = env.resources.get(sd.resources, {})
    if sd.per_scene:
        return {}
    if sd.resources in ("train", "eval") and int(res.get("num_workers", 1)) > 0:
        # The Ray Train workers (train) or the stage's own actors (eval) hold the resources: a coordinator that
        # held a CPU too could starve its workers on a small cluster.
        return {"num_cpus": 0, "max_retries": env.max_retries}
    return {
        "num_cpus": float(res.get("num_cpus", 1)),
        "num_gpus": float(res.get("num_gpus", 0)),
        "max_retries": env.max_retries,
    }
