"""Training stages on Ray Train: ScalingConfig from the cluster config, checkpoints, resume.

A stage calls ``ctx.train(loop, config)``; ``loop(session)`` runs on every worker::

    def loop(s: TrainSession):
        state = s.restore()                       # None on a fresh start
        step = state["step"] + 1 if state else 0
        for step in range(step, s.config["steps"]):
            ...
            s.report(step, {"loss": loss}, state={"step": step, "model": model.state_dict()})

With ``num_workers >= 1`` Ray Train runs a real worker group and ``FailureConfig(max_failures)``
restarts it; ``num_workers = 0`` runs the loop in-process (no start-up cost). Either way rank 0
also persists every reported checkpoint under the stage's checkpoint dir before reporting it,
and ``restore`` reads only that copy, so a restarted worker or a re-run resumes from the newest one.

Checkpoints are part of a cache entry's integrity. The layout is
``<workdir>/checkpoints/<stage>/<key>/steps/step_<step:09d>/`` with the state (``state.pt``) and, written last,
before the directory is renamed into place, a manifest ``CHECKPOINT.json``: the stage's cache key, the step, and
each file's size and sha256. A checkpoint is resumed from (``restore``, and the final state ``fit`` returns) only
when its manifest exists, names the same cache key, and every file it lists has that size and hash. One that fails
(a flipped byte, a truncated file, another key's checkpoint, or one written by a gdwm without manifests) is
deleted and named in a warning (the ``gdwm.training`` logger, and a note ``train/discarded_checkpoints/<name>.txt``
in the stage's MLflow run); the next older one is tried, and with none left training starts from step 0.
``discard_checkpoints`` removes every checkpoint of one stage key (the platform calls it when a cache entry is
invalidated or found corrupt, so the recompute starts from step 0).
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import re
import shutil
import tempfile
import uuid
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import ray.train
import ray.train.collective
import ray.train.torch
import torch
from ray.train import Checkpoint, FailureConfig, RunConfig, ScalingConfig
from ray.train.torch import TorchConfig, TorchTrainer

from gdwm.determinism import stage_start
from gdwm.simcluster import FAKE_GPUS_ENV

log = logging.getLogger(__name__)

STATE_FILE = "state.pt"
MANIFEST_FILE = "CHECKPOINT.json"
"""Written last into every checkpoint dir: ``{"format", "key", "step", "files": [{"path", "size", "sha256"}]}``."""
MANIFEST_FORMAT = "gdwm-checkpoint/1"
STEPS_DIR = "steps"
"""gdwm's own copies live in ``<checkpoint_dir>/steps``; Ray Train's storage is next to it."""
_STEP_RE = re.compile(r"step_(\d{9,})")
_NAME_RE = re.compile(r"[A-Za-z0-9_.\-]+")


@dataclass
class TrainSession:
    """What the loop sees on each worker."""

    config: dict
    tracker: Any
    local_ckpt_dir: str
    """Where gdwm persists every reported checkpoint itself (shared storage on a cluster)."""
    checkpoint_every: int
    key: str = ""
    """The stage's cache key: every checkpoint's manifest names it, and only checkpoints naming it are resumed."""
    progress: Any = None
    """The stage's ``gdwm.progress.Reporter`` (None outside a launch): rank 0's ``report`` sends each step to it."""
    total_steps: int | None = None
    """Steps the loop runs (``ctx.train(..., total_steps=N)``), shown as ``step / total`` with an ETA."""

    @property
    def rank(self) -> int:
        return ray.train.get_context().get_world_rank()

    @property
    def world_size(self) -> int:
        return ray.train.get_context().get_world_size()

    @property
    def device(self) -> torch.device:
        """This worker's torch device: its GPU where CUDA has one, else the CPU.

        Ray Train answers ``cuda:N`` for every worker it gave a GPU resource, also where the GPU is a Ray resource
        only (``cluster=sim`` without CUDA): the loop then runs its CPU kernels instead of failing in ``.to()``.
        """
        return ray.train.torch.get_device() if torch.cuda.is_available() else torch.device("cpu")

    def restore(self) -> dict | None:
        """The newest verified state (tensors and plain values, loaded with weights_only=True); None: start at 0.

        Only gdwm's own copies are read. Rank 0 picks the newest that verifies (one that fails is deleted and
        warned about) and every other rank loads the same one, so a group restarted after a lost worker or node
        resumes at one step on every rank.

        Ray Train's own copy (``ray.train.get_checkpoint()``) is deliberately not a fallback: rank 0 writes gdwm's
        copy synchronously before Ray hears of the report, into the same storage tree as Ray's (``storage_path``
        is this stage's checkpoint dir), so Ray's newest is never newer nor more reachable than gdwm's; and Ray
        Train restores its checkpoint list from that storage on a later ``fit`` of the same run name, so it would
        hand back exactly the checkpoints gdwm discarded as corrupt, from another attempt, unverified.
        """
        rank0 = self.rank == 0
        latest = _newest_verified(self.local_ckpt_dir, self.key, tracker=self.tracker)[0] if rank0 else None
        if self.world_size > 1:
            # Every rank resumes from rank 0's choice: a rank that looked for itself could find the checkpoint rank 0
            # writes a moment later, start a step ahead, and leave the group waiting forever in ray.train.report.
            chosen = ray.train.collective.broadcast_from_rank_zero(str(latest) if latest is not None else None)
            latest = Path(chosen) if chosen is not None else None
        if latest is None:
            return None
        return torch.load(latest / STATE_FILE, map_location="cpu", weights_only=True)

    def should_checkpoint(self, step: int) -> bool:
        return self.checkpoint_every > 0 and (step + 1) % self.checkpoint_every == 0

    def report(self, step: int, metrics: Mapping[str, float], state: dict | None = None) -> None:
        """Log metrics at ``step`` (rank 0) and, with ``state``, report a checkpoint."""
        metrics = {k: float(v) for k, v in metrics.items()}
        if self.rank == 0 and self.tracker is not None:
            self.tracker.log_metrics(metrics, step=step)
        if self.rank == 0 and self.progress is not None:
            loss = metrics.get("loss", next((v for k, v in metrics.items() if "loss" in k), None))
            self.progress.step(step + 1, self.total_steps, loss)
        if state is None:
            ray.train.report({**metrics, "step": step})
            return
        with tempfile.TemporaryDirectory() as d:
            if self.rank == 0:
                torch.save(state, Path(d) / STATE_FILE)
                write_checkpoint_manifest(Path(d), self.key, step)
                # Persisted synchronously before Ray hears of it (see restore); in-process mode Ray keeps no copy.
                _persist_local(Path(d), Path(self.local_ckpt_dir), step)
            ckpt = Checkpoint.from_directory(d) if self.rank == 0 else None
            ray.train.report({**metrics, "step": step}, checkpoint=ckpt)


def warmup_cosine_lr(step: int, base_lr: float, warmup_steps: int, total_steps: int, floor: float = 0.1) -> float:
    """Linear warm-up over ``warmup_steps``, then cosine decay to ``floor * base_lr`` at ``total_steps``."""
    if warmup_steps and step < warmup_steps:
        return base_lr * (step + 1) / warmup_steps
    progress = min(1.0, (step - warmup_steps) / max(1, total_steps - warmup_steps))
    return base_lr * (floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * progress)))


# ---- checkpoint manifests ----------------------------------------------------------------------------------------
def _sha256(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def _files(d: Path) -> list[str]:
    """Every regular file under ``d`` but the manifest, as sorted posix paths relative to ``d``."""
    return sorted(p.relative_to(d).as_posix() for p in d.rglob("*") if p.is_file() and p.name != MANIFEST_FILE)


def write_checkpoint_manifest(d: str | Path, key: str, step: int) -> dict:
    """Hash every file in checkpoint dir ``d`` and write ``CHECKPOINT.json`` (last, so it vouches for them all)."""
    d = Path(d)
    manifest = {
        "format": MANIFEST_FORMAT,
        "key": key,
        "step": int(step),
        "files": [{"path": f, "size": (d / f).stat().st_size, "sha256": _sha256(d / f)} for f in _files(d)],
    }
    (d / MANIFEST_FILE).write_text(json.dumps(manifest, indent=1, sort_keys=True))
    return manifest


def verify_checkpoint(d: str | Path, key: str) -> str | None:
    """Why checkpoint dir ``d`` must not be resumed from by stage key ``key``, or None when it verifies: its
    manifest exists, names ``key`` (and, for a ``step_N`` dir, step N), lists the state file, and every file it
    lists has the recorded size and sha256. Files the manifest does not list are never read, so they don't count."""
    d = Path(d)
    try:
        m = json.loads((d / MANIFEST_FILE).read_text())
    except FileNotFoundError:
        return f"no {MANIFEST_FILE} (written by an older gdwm, or never finished)"
    except (OSError, ValueError) as e:
        return f"{MANIFEST_FILE} unreadable: {e}"
    if not isinstance(m, dict) or m.get("format") != MANIFEST_FORMAT or not isinstance(m.get("files"), list):
        return f"{MANIFEST_FILE} is not a {MANIFEST_FORMAT} manifest"
    if m.get("key") != key:
        return f"written for stage key {str(m.get('key'))[:12]}, not this stage's key {key[:12]}"
    if (s := _STEP_RE.fullmatch(d.name)) and int(s.group(1)) != m.get("step"):
        return f"{MANIFEST_FILE} is for step {m.get('step')}, not {int(s.group(1))}"
    try:
        listed = {fe["path"]: fe for fe in m["files"]}
        if STATE_FILE not in listed:
            return f"{STATE_FILE} is not listed in {MANIFEST_FILE}"
        for path, fe in listed.items():
            f = d / path
            if not f.resolve().is_relative_to(d.resolve()):
                return f"{path}: outside the checkpoint"
            if not f.is_file():
                return f"{path}: missing"
            if (size := f.stat().st_size) != fe["size"]:
                return f"{path}: size {size} != {fe['size']} in {MANIFEST_FILE}"
            if (digest := _sha256(f)) != fe["sha256"]:
                return f"{path}: sha256 {digest[:12]} != {str(fe['sha256'])[:12]} in {MANIFEST_FILE}"
    except (KeyError, TypeError) as e:
        return f"{MANIFEST_FILE} malformed: {e!r}"
    return None


def _discard(d: Path, reason: str, tracker: Any) -> None:
    """Delete a checkpoint that failed verification (moved aside first: readers never see half of it), and warn."""
    note = f"discarded checkpoint {d}: {reason}"
    log.warning("gdwm: %s", note)
    if tracker is not None:
        try:
            tracker.log_text(note + "\n", f"train/discarded_checkpoints/{d.name}.txt")
        except Exception:  # the warning above is the record; tracking trouble must not stop a resume
            log.exception("gdwm: could not record the discarded checkpoint %s in the tracker", d)
    trash = d.with_name(f".discarded-{d.name}-{uuid.uuid4().hex[:8]}")
    try:
        d.rename(trash)
    except FileNotFoundError:  # another process discarded it already
        return
    shutil.rmtree(trash, ignore_errors=True)


def _step_dirs(root: str | Path | None) -> list[Path]:
    """``step_*`` dirs under ``root``, newest (highest step) first."""
    if root is None or not Path(root).is_dir():
        return []
    found = [p for p in Path(root).iterdir() if _STEP_RE.fullmatch(p.name) and p.is_dir()]
    return sorted(found, key=lambda p: int(p.name[5:]), reverse=True)


def _newest_verified(
    root: str | Path | None, key: str, discard: bool = True, tracker: Any = None
) -> tuple[Path | None, list[tuple[Path, str]]]:
    """The newest checkpoint under ``root`` that verifies for ``key``, and the newer ones that failed (deleted and
    warned about when ``discard``)."""
    failed = []
    for d in _step_dirs(root):
        reason = verify_checkpoint(d, key)
        if reason is None:
            return d, failed
        failed.append((d, reason))
        if discard:
            _discard(d, reason, tracker)
        else:
            log.warning("gdwm: skipping checkpoint %s: %s", d, reason)
    return None, failed


def latest_local_checkpoint(
    root: str | Path | None, key: str, discard: bool = True, tracker: Any = None
) -> Path | None:
    """The newest checkpoint dir under ``root`` (a stage key's ``steps/``) that verifies for ``key``; newer ones
    that fail are deleted and warned about (only skipped with ``discard=False``). None: start from step 0."""
    return _newest_verified(root, key, discard, tracker)[0]


def discard_checkpoints(checkpoint_root: str | Path, stage: str, key: str) -> int:
    """Remove everything under ``<checkpoint_root>/<stage>/<key>``: gdwm's ``steps/``, Ray Train's storage and
    zoo downloads of that stage key, so its next run starts from step 0. Returns how many checkpoints (gdwm's
    ``step_*`` dirs and Ray Train's ``checkpoint_*`` dirs) were removed; 0 when there was nothing."""
    for what, name in (("stage", stage), ("key", key)):
        if not _NAME_RE.fullmatch(name) or name in (".", ".."):
            raise ValueError(f"discard_checkpoints: {what} {name!r} is not a plain name")
    d = Path(checkpoint_root) / stage / key
    if not d.is_dir():
        return 0
    count = sum(
        1 for p in d.rglob("*") if p.is_dir() and (_STEP_RE.fullmatch(p.name) or p.name.startswith("checkpoint_"))
    )
    trash = d.with_name(f".discarded-{key}-{uuid.uuid4().hex[:8]}")
    try:
        d.rename(trash)  # the key's dir vanishes at once; a concurrent reader sees all of it or nothing
    except FileNotFoundError:
        return 0
    shutil.rmtree(trash, ignore_errors=True)
    log.info("gdwm: discarded %d checkpoint(s) of %s/%s", count, stage, key[:12])
    return count


def _persist_local(src: Path, root: Path, step: int) -> Path:
    """Copy checkpoint dir ``src`` to ``root/step_<step>``: its files, then its manifest last, then an atomic rename
    into place (an older copy of the same step is moved aside first and deleted after)."""
    root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=root, prefix=".tmp-"))
    shutil.copytree(src, tmp, dirs_exist_ok=True, ignore=shutil.ignore_patterns(MANIFEST_FILE))
    if (src / MANIFEST_FILE).is_file():
        shutil.copy2(src / MANIFEST_FILE, tmp / MANIFEST_FILE)
    final = root / f"step_{step:09d}"
    old = None
    if final.exists():
        old = final.with_name(f".replaced-{final.name}-{uuid.uuid4().hex[:8]}")
        final.rename(old)
    tmp.rename(final)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    return final


def _worker_entry(payload: dict) -> None:
    loop: Callable[[TrainSession], None] = payload["loop"]
    # a worker process of Ray Train's group starts from the same state as the stage task did (gdwm.determinism)
    stage_start(payload["seed"], payload["num_cpus"], payload["deterministic"])
    if payload.get("tracker") is not None and ray.train.get_context().get_world_rank() == 0:
        payload["tracker"].log_text(f"world_size={ray.train.get_context().get_world_size()}", "train/world.txt")
    loop(
        TrainSession(
            payload["config"],
            payload["tracker"],
            payload["local_ckpt_dir"],
            payload["checkpoint_every"],
            payload.get("key", ""),
            payload.get("progress"),
            payload.get("total_steps"),
        )
    )
    if payload.get("tracker") is not None and ray.train.get_context().get_world_rank() == 0:
        payload["tracker"].flush()


def fit(ctx, loop: Callable[[TrainSession], None], loop_config: dict, total_steps: int | None = None) -> TrainResult:
    res = ctx.resources
    workers = int(res.get("num_workers", 1))
    gpus = float(res.get("num_gpus", 0))
    settings = ctx.train_settings
    local = workers == 0
    payload = {
        "loop": loop,
        "config": loop_config,
        "tracker": ctx.tracker,
        "local_ckpt_dir": str(ctx.checkpoint_dir / STEPS_DIR),
        "checkpoint_every": int(settings.get("checkpoint_every", 1)),
        "key": ctx.key,
        "seed": ctx.seed or 0,
        "num_cpus": float(res.get("num_cpus", 1)),
        "deterministic": ctx.deterministic,
        "progress": ctx.progress_sink,
        "total_steps": total_steps,
    }
    scaling = ScalingConfig(
        num_workers=workers,
        use_gpu=gpus > 0,
        resources_per_worker=None
        if local
        else {"CPU": float(res.get("num_cpus", 1)), **({"GPU": gpus} if gpus else {})},
    )
    run = RunConfig(
        name=f"train-{ctx.key[:16]}",
        # under the workdir, which every node sees (the PVC on k8s): a group restarted on another node, or a
        # stage task Ray retried there after a node loss, resumes from the last checkpoint any node wrote
        storage_path=str(ctx.checkpoint_dir),
        failure_config=FailureConfig(max_failures=int(settings.get("max_failures", 2))),
    )
    # GPUs that are Ray resources only (cluster=sim without CUDA): the group talks over gloo, not NCCL
    torch_config = TorchConfig(backend="gloo") if gpus and os.environ.get(FAKE_GPUS_ENV) else None
    trainer = TorchTrainer(_worker_entry, train_loop_config=payload, scaling_config=scaling, run_config=run,
                           torch_config=torch_config)  # fmt: skip
    result = trainer.fit()
    state = _final_state(payload["local_ckpt_dir"], ctx.key, ctx.tracker)
    return TrainResult(state, dict(result.metrics or {}))


@dataclass
class TrainResult:
    state: dict | None
    """The last reported state (None if the loop never reported one)."""
    metrics: dict


def _final_state(local_dir: str, key: str, tracker: Any = None) -> dict | None:
    """The last reported state: gdwm's own copy (always written, also when the loop had nothing left to do).

    The newest checkpoint is the last one reported (``restore`` already discarded older attempts' bad ones), so if
    it fails verification now it is discarded and the stage fails: publishing an older step's state as the result
    would be wrong, and the next run resumes from the last intact checkpoint. Ray's ``result.checkpoint`` is not a
    fallback, for the reasons in ``TrainSession.restore`` (in-process mode it even names a deleted temp dir).
    """
    latest, failed = _newest_verified(local_dir, key, discard=True, tracker=tracker)
    if failed:
        d, reason = failed[0]
        raise RuntimeError(
            f"the last training checkpoint {d} failed verification ({reason}); it was discarded rather than "
            f"publish {'the state of ' + latest.name if latest else 'no state'} instead; run again to resume from "
            "the last intact checkpoint"
        )
    if latest is None:
        return None
    return torch.load(latest / STATE_FILE, map_location="cpu", weights_only=True)
