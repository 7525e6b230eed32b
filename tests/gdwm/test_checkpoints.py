"""Training checkpoints are part of a cache entry's integrity (gdwm.training).

In-process tests run ``gdwm.training.fit`` with ``num_workers=0`` (Ray Train's local mode: no cluster) on a
stand-in stage context; the end-to-end test runs the real CLI on the toy pipeline (tests/gdwm/stages.py), whose
training stages report a checkpoint at every step.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import mlflow
import pytest
import torch

from gdwm.cache import Cache
from gdwm.training import (
    MANIFEST_FILE,
    STATE_FILE,
    discard_checkpoints,
    fit,
    latest_local_checkpoint,
    verify_checkpoint,
)
from tests.gdwm.toydata import make_dataset

pytestmark = pytest.mark.heavy(2)

REPO = Path(__file__).resolve().parents[2]
KEY = "a" * 64
OTHER = "b" * 64
STEPS = 4


class Notes:
    """A tracker that keeps what the training loop logs."""

    def __init__(self):
        self.metrics: list[tuple[dict, int | None]] = []
        self.texts: dict[str, str] = {}

    def log_metrics(self, metrics, step=None):
        self.metrics.append((dict(metrics), step))

    def log_text(self, text, artifact_file):
        self.texts[artifact_file] = text

    def flush(self):
        pass

    def starts(self) -> list[float]:
        """The step each attempt started from, once per attempt."""
        return sorted({m["start"] for m, _ in self.metrics})

    def discarded(self) -> dict[str, str]:
        return {k: v for k, v in self.texts.items() if k.startswith("train/discarded_checkpoints/")}

    def steps(self) -> list[int]:
        return [s for _, s in self.metrics]


def _loop(s) -> None:
    state = s.restore()
    start = state["step"] + 1 if state else 0
    w = state["w"] if state else torch.zeros(4)
    for step in range(start, s.config["steps"]):
        w = w * 0.5 + torch.arange(4.0) * (step + 1)
        s.report(step, {"loss": 1.0 / (step + 1), "start": float(start)}, state={"step": step, "w": w})


def _fit(root: Path, key: str = KEY, loop=_loop) -> tuple[dict | None, Notes]:
    notes = Notes()
    ctx = SimpleNamespace(
        key=key,
        checkpoint_dir=root / "tokenizer" / key,
        resources={"num_workers": 0, "num_cpus": 1},
        train_settings={"checkpoint_every": 1, "max_failures": 0},
        tracker=notes,
        seed=0,
        deterministic=False,
        progress_sink=None,  # no progress actor: steps are reported nowhere
    )
    return fit(ctx, loop, {"steps": STEPS}).state, notes


def _steps_dir(root: Path, key: str = KEY) -> Path:
    return root / "tokenizer" / key / "steps"


def _flip(f: Path) -> None:
    data = bytearray(f.read_bytes())
    data[len(data) // 2] ^= 0x01
    f.write_bytes(bytes(data))


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> tuple[Path, dict]:
    """A clean training run: its checkpoint root and final state."""
    root = tmp_path_factory.mktemp("clean")
    state, notes = _fit(root)
    assert notes.starts() == [0.0] and notes.steps() == [0, 1, 2, 3]
    return root, state


def _copy(clean_root: Path, dst: Path) -> Path:
    shutil.copytree(clean_root, dst)
    return dst


def _names(root: Path, key: str = KEY) -> list[str]:
    return sorted(p.name for p in _steps_dir(root, key).iterdir())


def _same_checkpoints(a: Path, b: Path) -> None:
    """Both roots hold byte-identical state files for the same steps, and each one verifies."""
    assert _names(a) == _names(b) == [f"step_{i:09d}" for i in range(STEPS)]
    for name in _names(a):
        assert (_steps_dir(a) / name / STATE_FILE).read_bytes() == (_steps_dir(b) / name / STATE_FILE).read_bytes()
        assert verify_checkpoint(_steps_dir(a) / name, KEY) is None


def test_every_checkpoint_has_a_manifest_with_key_step_and_hashes(clean):
    root, state = clean
    assert state["step"] == STEPS - 1
    for i in range(STEPS):
        d = _steps_dir(root) / f"step_{i:09d}"
        m = json.loads((d / MANIFEST_FILE).read_text())
        assert m["key"] == KEY and m["step"] == i and m["format"] == "gdwm-checkpoint/1"
        data = (d / STATE_FILE).read_bytes()
        assert m["files"] == [{"path": STATE_FILE, "size": len(data), "sha256": hashlib.sha256(data).hexdigest()}]
        assert torch.load(d / STATE_FILE, weights_only=True)["step"] == i


def test_corrupted_newest_checkpoint_is_discarded_and_training_resumes_from_the_last_intact_one(
    clean, tmp_path, caplog
):
    clean_root, clean_state = clean
    root = _copy(clean_root, tmp_path / "ck")
    _flip(_steps_dir(root) / "step_000000003" / STATE_FILE)
    assert verify_checkpoint(_steps_dir(root) / "step_000000003", KEY).startswith("state.pt: sha256 ")
    with caplog.at_level(logging.WARNING, logger="gdwm.training"):
        state, notes = _fit(root)
    # step 3 was retrained from step 2's state, nothing before it
    assert notes.starts() == [3.0] and notes.steps() == [3]
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "step_000000003" in warnings[0] and "sha256" in warnings[0]
    assert list(notes.discarded()) == ["train/discarded_checkpoints/step_000000003.txt"]
    assert str(_steps_dir(root) / "step_000000003") in notes.texts["train/discarded_checkpoints/step_000000003.txt"]
    # the same weights as the clean run, and the rewritten checkpoint is byte-identical to the clean one
    assert state["step"] == clean_state["step"] and torch.equal(state["w"], clean_state["w"])
    _same_checkpoints(root, clean_root)


def test_no_intact_checkpoint_restarts_from_step_0(clean, tmp_path, caplog):
    clean_root, clean_state = clean
    root = _copy(clean_root, tmp_path / "ck")
    for name in _names(root):
        _flip(_steps_dir(root) / name / STATE_FILE)
    (_steps_dir(root) / "step_000000001" / STATE_FILE).write_bytes(b"")  # a truncated one fails on its size
    with caplog.at_level(logging.WARNING, logger="gdwm.training"):
        state, notes = _fit(root)
    assert notes.starts() == [0.0] and notes.steps() == [0, 1, 2, 3]
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 4
    assert all(f"step_{i:09d}" in w for i, w in zip([3, 2, 1, 0], warned, strict=True))
    assert "state.pt: size 0 != " in warned[2]
    assert len(notes.discarded()) == 4
    assert torch.equal(state["w"], clean_state["w"])
    _same_checkpoints(root, clean_root)


def test_checkpoint_of_another_key_is_not_used(clean, tmp_path, caplog):
    clean_root, clean_state = clean
    root = tmp_path / "ck"
    # key OTHER's steps/ holds key KEY's checkpoints (a copied dir): every one names KEY in its manifest
    shutil.copytree(_steps_dir(clean_root), _steps_dir(root, OTHER))
    assert latest_local_checkpoint(_steps_dir(root, OTHER), OTHER, discard=False) is None
    assert latest_local_checkpoint(_steps_dir(root, OTHER), KEY, discard=False).name == "step_000000003"
    caplog.clear()  # the look-ups above only skipped them, with a warning each
    with caplog.at_level(logging.WARNING, logger="gdwm.training"):
        state, notes = _fit(root, OTHER)
    assert notes.starts() == [0.0] and notes.steps() == [0, 1, 2, 3]
    assert torch.equal(state["w"], clean_state["w"])
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 4 and all(f"written for stage key {KEY[:12]}, not this stage's key" in w for w in warned)
    assert all(w.startswith("gdwm: discarded checkpoint ") for w in warned)
    # what is there now is OTHER's own
    for name in _names(root, OTHER):
        assert json.loads((_steps_dir(root, OTHER) / name / MANIFEST_FILE).read_text())["key"] == OTHER
    assert latest_local_checkpoint(_steps_dir(root, OTHER), KEY, discard=False) is None


def test_checkpoint_without_manifest_is_not_trusted(clean, tmp_path, caplog):
    """Checkpoints of an older gdwm have no manifest: the newest two lose it, the older two keep it."""
    clean_root, clean_state = clean
    root = _copy(clean_root, tmp_path / "ck")
    for name in ("step_000000002", "step_000000003"):
        (_steps_dir(root) / name / MANIFEST_FILE).unlink()
    with caplog.at_level(logging.WARNING, logger="gdwm.training"):
        state, notes = _fit(root)
    assert notes.starts() == [2.0] and notes.steps() == [2, 3]
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 2 and all("no CHECKPOINT.json (written by an older gdwm" in w for w in warned)
    assert torch.equal(state["w"], clean_state["w"])
    _same_checkpoints(root, clean_root)
    # none at all with a manifest: step 0
    root2 = _copy(clean_root, tmp_path / "ck2")
    for name in _names(root2):
        (_steps_dir(root2) / name / MANIFEST_FILE).unlink()
    state, notes = _fit(root2)
    assert notes.starts() == [0.0] and torch.equal(state["w"], clean_state["w"])


def test_discard_false_only_skips(clean, tmp_path):
    """What ranks other than 0 do: skip a bad checkpoint without deleting it (rank 0 deletes it)."""
    root = _copy(clean[0], tmp_path / "ck")
    _flip(_steps_dir(root) / "step_000000003" / STATE_FILE)
    assert latest_local_checkpoint(_steps_dir(root), KEY, discard=False).name == "step_000000002"
    assert len(_names(root)) == 4
    assert latest_local_checkpoint(_steps_dir(root), KEY).name == "step_000000002"
    assert _names(root) == [f"step_{i:09d}" for i in range(3)]
    assert latest_local_checkpoint(tmp_path / "none", KEY) is None


def test_manifest_for_another_step_fails(clean, tmp_path):
    root = _copy(clean[0], tmp_path / "ck")
    d3, d2 = _steps_dir(root) / "step_000000003", _steps_dir(root) / "step_000000002"
    shutil.rmtree(d3)
    shutil.copytree(d2, d3)  # step 2's checkpoint under step 3's name
    assert verify_checkpoint(d3, KEY) == "CHECKPOINT.json is for step 2, not 3"


def test_a_final_checkpoint_that_fails_verification_fails_the_stage(tmp_path):
    """The last checkpoint is the result: if it fails its hash, the stage fails instead of publishing an older one."""

    def corrupting_loop(s):
        _loop(s)
        _flip(Path(s.local_ckpt_dir) / "step_000000003" / STATE_FILE)

    with pytest.raises(RuntimeError, match=r"step_000000003 failed verification \(state.pt: sha256 .*step_000000002"):
        _fit(tmp_path, loop=corrupting_loop)
    assert _names(tmp_path) == [f"step_{i:09d}" for i in range(3)]  # discarded; the next run resumes from step 2
    state, notes = _fit(tmp_path)
    assert notes.starts() == [3.0] and state["step"] == 3


def test_discard_checkpoints_removes_one_key_and_counts(clean, tmp_path):
    root = tmp_path / "ck"
    shutil.copytree(clean[0], root)
    _fit(root, OTHER)
    # Ray Train's storage of the key (num_workers >= 1) sits next to gdwm's steps/
    for i in range(2):
        ray_ckpt = root / "tokenizer" / KEY / f"train-{KEY[:16]}" / f"checkpoint_2026-01-01_00-00-0{i}.000000"
        ray_ckpt.mkdir(parents=True)
        (ray_ckpt / STATE_FILE).write_bytes(b"x")
    (root / "lora" / KEY / "steps" / "step_000000000").mkdir(parents=True)  # another stage, same key
    assert discard_checkpoints(root, "tokenizer", KEY) == STEPS + 2
    assert not (root / "tokenizer" / KEY).exists()
    assert sorted(p.name for p in (root / "tokenizer").iterdir()) == [OTHER]  # nothing left aside
    assert _names(root, OTHER) == [f"step_{i:09d}" for i in range(STEPS)]
    assert all(verify_checkpoint(_steps_dir(root, OTHER) / n, OTHER) is None for n in _names(root, OTHER))
    assert (root / "lora" / KEY / "steps" / "step_000000000").is_dir()
    assert discard_checkpoints(root, "tokenizer", KEY) == 0
    assert discard_checkpoints(str(root), "lora", KEY) == 1
    for stage, key in (("tokenizer", ""), ("tokenizer", ".."), ("../x", KEY), ("tokenizer", "a/b")):
        with pytest.raises(ValueError, match="is not a plain name"):
            discard_checkpoints(root, stage, key)
    assert _names(root, OTHER) == [f"step_{i:09d}" for i in range(STEPS)]


# ---- end to end: the CLI on the toy pipeline -----------------------------------------------------------------------
def _gdwm_run(root: Path, *overrides: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith("GDWM_TEST_")}
    env.update(PYTHONPATH=str(REPO), GDWM_CONF_PATH=str(REPO / "tests" / "conf"), GDWM_TEST_DIR=str(root))
    args = ["experiment=toy", f"workdir={root / 'w'}", f"data.root={root / 'ds'}", "targets=[tokenizer]"]
    r = subprocess.run(
        [sys.executable, "-m", "gdwm", "run", *args, *overrides], env=env, capture_output=True, text=True, timeout=300
    )
    assert r.returncode == 0, f"exit {r.returncode}\nSTDOUT\n{r.stdout[-3000:]}\nSTDERR\n{r.stderr[-5000:]}"
    return r


def _tokenizer_runs(root: Path) -> list:
    """The tokenizer's stage runs, oldest first (a recompute of a finished key gets a run of its own)."""
    client = mlflow.MlflowClient(f"sqlite:///{(root / 'w').resolve()}/mlflow.db")
    exp = client.get_experiment_by_name("gdwm")
    runs = [x for x in client.search_runs([exp.experiment_id]) if x.data.tags.get("gdwm.stage") == "tokenizer"]
    return sorted(runs, key=lambda r: r.info.start_time)


def _starts(root: Path) -> list[list[float]]:
    """Per tokenizer run, the ``start`` step its training loop logged at every step it trained."""
    client = mlflow.MlflowClient(f"sqlite:///{(root / 'w').resolve()}/mlflow.db")
    return [sorted(m.value for m in client.get_metric_history(r.info.run_id, "start")) for r in _tokenizer_runs(root)]


def test_recompute_after_a_corrupted_checkpoint_publishes_a_clean_runs_weights(tmp_path):
    make_dataset(tmp_path / "ds")
    _gdwm_run(tmp_path)
    cache = Cache(tmp_path / "w" / "cache")
    (clean,) = cache.entries("tokenizer")
    clean_weights = (cache.materialize(clean) / "weights.npy").read_bytes()
    steps = tmp_path / "w" / "checkpoints" / "tokenizer" / clean.key / "steps"
    assert sorted(p.name for p in steps.iterdir()) == [f"step_{i:09d}" for i in range(4)]
    # the entry is gone (deleted by hand, or never published), its checkpoints are not; the newest is corrupt
    shutil.rmtree(cache.materialize(clean))
    _flip(steps / "step_000000003" / STATE_FILE)
    (tmp_path / "executions.log").write_text("")

    r = _gdwm_run(tmp_path, "run.worker_logs=true")
    assert [line.split()[0] for line in (tmp_path / "executions.log").read_text().splitlines()] == ["tokenizer"]
    assert f"discarded checkpoint {steps / 'step_000000003'}: state.pt: sha256 " in r.stderr
    (again,) = cache.entries("tokenizer")
    assert again.key == clean.key and again.files == clean.files  # the same bytes as the clean run published
    assert (cache.materialize(again) / "weights.npy").read_bytes() == clean_weights
    # retrained step 3 only, from step 2's checkpoint; the discarded one is named in the stage's MLflow run
    client = mlflow.MlflowClient(f"sqlite:///{(tmp_path / 'w').resolve()}/mlflow.db")
    first, run = _tokenizer_runs(tmp_path)  # the recompute has its own run, linked to the first
    assert run.data.tags["gdwm.recomputes"] == first.info.run_id
    assert _starts(tmp_path) == [[0, 0, 0, 0], [3]]
    note = client.download_artifacts(
        run.info.run_id, "train/discarded_checkpoints/step_000000003.txt", str(tmp_path / "dl")
    )
    assert "step_000000003: state.pt: sha256 " in Path(note).read_text()
    assert verify_checkpoint(steps / "step_000000003", clean.key) is None

    # The executor discards a key's checkpoints before it recomputes the entry: after a corrupt entry (its
    # checkpoints, intact or not, may be what produced it) and when forced (cache.reuse=none means train again,
    # not resume at the last step). Either way training starts at step 0 and publishes the same bytes.
    _flip(cache.materialize(again) / "weights.npy")  # the entry is corrupt, its checkpoints intact
    (tmp_path / "executions.log").write_text("")
    _gdwm_run(tmp_path)
    assert [line.split()[0] for line in (tmp_path / "executions.log").read_text().splitlines()] == ["tokenizer"]
    assert _starts(tmp_path) == [[0, 0, 0, 0], [3], [0, 0, 0, 0]]  # a third run, from step 0: nothing resumed
    assert (cache.materialize(cache.lookup("tokenizer", clean.key)) / "weights.npy").read_bytes() == clean_weights
    assert sorted(p.name for p in steps.iterdir()) == [f"step_{i:09d}" for i in range(4)]
    _gdwm_run(tmp_path, "cache.reuse=none")
    assert _starts(tmp_path) == [[0, 0, 0, 0], [3], [0, 0, 0, 0], [0, 0, 0, 0]]
    assert (cache.materialize(cache.lookup("tokenizer", clean.key)) / "weights.npy").read_bytes() == clean_weights
