"""QA samples of the world model: instruction, answer, the frame's distilled Gaussians, images, ego trajectory.

Legend: ``N`` Gaussians, ``T`` waypoints, ``C`` code width d_z.
"""

from __future__ import annotations

import json
import logging
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np
import torch

from model_zoo.config import PathSource, SelectorConfig
from model_zoo.lru import LRU
from model_zoo.selectors import route_path
from pipelines.data.layout import GAUSS_TOKEN, ROUTES_FILE, TASKS, DataError
from pipelines.data.reader import GSQADataset, gaussians_from_table, read_arrow

log = logging.getLogger(__name__)

T = TypeVar("T")


@dataclass(frozen=True)
class QASample:
    sample_id: str
    scene: str
    frame: int
    task: str
    instruction: str
    answer: str
    views: tuple[str, ...]
    category: str = ""
    """Finer than ``task`` (e.g. ``region_description``): the evaluate stage maps categories onto benchmark metrics."""


def _turns(conversations: Sequence[Mapping], sample_id: str) -> tuple[str, str]:
    """(human, gpt) of a one-turn conversation, in our ``from``/``value`` or the release's ``role``/``content``."""
    human = [
        c.get("value", c.get("content")) for c in conversations if c.get("from", c.get("role")) in ("human", "user")
    ]
    gpt = [
        c.get("value", c.get("content")) for c in conversations if c.get("from", c.get("role")) in ("gpt", "assistant")
    ]
    if not human or not gpt:
        raise DataError(f"{sample_id}: conversation needs a human and a gpt turn, got {list(conversations)}")
    return human[0], gpt[0]


def load_samples(
    ds: GSQADataset, split: str, scene_dirs: Mapping[str, Path], *, need_gaussians: bool
) -> tuple[list[QASample], Counter]:
    """The ``split`` QA of ``ds`` whose frame has Gaussians (when ``need_gaussians``), and why others were skipped.

    Frames that reconstruction QC excluded, and scenes whose upstream failed, have no Gaussian file: their samples
    are counted under ``skipped`` (never silently dropped) and the caller logs the counts.
    """
    samples, skipped = [], Counter()
    for row in ds.qa(split=split).to_pylist():
        sid = row["sample_id"]
        human, gpt = _turns(row["conversations"], sid)
        views = tuple(row["views"])
        s = QASample(sid, row["scene_token"], int(row["frame_idx"]), row["task"], human, gpt, views, row["category"])
        if need_gaussians:
            if s.scene not in scene_dirs:
                skipped["scene_without_gaussians"] += 1
                continue
            if not gaussians_path(scene_dirs[s.scene], s.frame).is_file():
                skipped["frame_excluded_by_qc"] += 1
                continue
            if GAUSS_TOKEN not in s.instruction:
                skipped["instruction_without_gauss_placeholder"] += 1
                continue
        samples.append(s)
    return samples, skipped


def row_samples(ds: GSQADataset, split: str, scene_dirs: Mapping[str, Path]) -> tuple[list[QASample], Counter]:
    """The ``split`` samples a stage trains or monitors on, the same for every row of a table: those whose frame has
    Gaussians and whose instruction has the placeholder, whether or not the row reads Gaussian tokens (an
    image-only row on other samples than the Gaussian rows would differ from them in its data as well)."""
    return load_samples(ds, split, scene_dirs, need_gaussians=True)


def balanced_subset(samples: Sequence[QASample], n: int) -> list[QASample]:
    """At most ``n`` of ``samples``, as even a share of every task family as the families allow (a family with
    fewer samples gives its unused share to the others), each family's share spread evenly over its samples (so
    over scenes and frames), returned in the original order. Deterministic; ``n <= 0`` keeps everything.

    The first ``n`` samples would be the first frames of the first val scene: a few families, one scenario."""
    if n <= 0 or n >= len(samples):
        return list(samples)
    groups: dict[str, list[int]] = {}
    for i, s in enumerate(samples):
        groups.setdefault(s.task, []).append(i)
    quota, taken = dict.fromkeys(groups, 0), 0
    while taken < n:  # round robin; n < len(samples), so some family always has one left
        for t in groups:
            if quota[t] < len(groups[t]) and taken < n:
                quota[t] += 1
                taken += 1
    keep = sorted(g[(k * len(g)) // quota[t]] for t, g in groups.items() for k in range(quota[t]))
    return [samples[i] for i in keep]


def task_counts(samples: Sequence[QASample]) -> dict[str, int]:
    """Samples per task family, every family of the paper's QA listed (0 when it has none)."""
    counts = Counter(s.task for s in samples)
    return {t: counts[t] for t in (*TASKS, *sorted(set(counts) - set(TASKS)))}


def gaussians_path(scene_dir: Path, frame: int) -> Path:
    return scene_dir / "gaussians" / f"{frame:05d}.arrow"


def task_probabilities(counts: Mapping[str, int], alpha: float) -> dict[str, float]:
    """Eq. P_m = n_m^alpha_s / sum_k n_k^alpha_s (Sec. Scene Understanding with Gaussian World Tokens)."""
    weights = {m: float(n) ** alpha for m, n in counts.items() if n > 0}
    total = sum(weights.values())
    return {m: w / total for m, w in weights.items()}


class TaskSampler:
    """Batches drawn with task-aware probabilities; batch ``step`` depends only on (seed, step), so a resumed run
    draws exactly the batches an uninterrupted one would have."""

    def __init__(self, samples: Sequence[QASample], alpha: float, seed: int):
        if not samples:
            raise DataError(
                "task-aware sampling: no training samples (every QA sample was skipped or the split is empty)"
            )
        self.by_task: dict[str, list[int]] = {}
        for i, s in enumerate(samples):
            self.by_task.setdefault(s.task, []).append(i)
        self.tasks = sorted(self.by_task)
        probs = task_probabilities({t: len(self.by_task[t]) for t in self.tasks}, alpha)
        self.probs = np.array([probs[t] for t in self.tasks])
        self.seed = seed

    def batch(self, step: int, size: int) -> list[int]:
        rng = np.random.default_rng([self.seed, step])
        tasks = rng.choice(len(self.tasks), size=size, p=self.probs)
        return [int(rng.choice(self.by_task[self.tasks[t]])) for t in tasks]


def ego_trajectory_xy(ego2world_F44: np.ndarray, frame: int, frames: int) -> np.ndarray:
    """[T, 2] ego-path prior in the current ego frame: the last ``frames`` ego positions and as many more ahead at the
    last step's velocity. Built from the past only, so planning answers never leak into the selection."""
    lo = max(0, frame - frames)
    world_to_ego = np.linalg.inv(ego2world_F44[frame])
    past = np.einsum("ij,fj->fi", world_to_ego, ego2world_F44[lo : frame + 1, :, 3])[:, :2]
    step = past[-1] - past[-2] if len(past) >= 2 else np.zeros(2)
    ahead = past[-1] + step * np.arange(1, frames + 1)[:, None]
    return np.concatenate([past, ahead]).astype(np.float32)


class FrameStore:
    """Per-frame inputs, loaded on first use and kept in small LRUs (a training run's steps and a sweep's trials read
    the same frames again): each frame's Gaussians (``capacity`` frames), camera views (``image_bytes`` of decoded
    pixels) and what a caller derives from one frame alone (``derived``: a selector's candidates)."""

    def __init__(
        self,
        ds: GSQADataset,
        scene_dirs: Mapping[str, Path],
        weather: str,
        trajectory_frames: int,
        capacity: int = 256,
        image_bytes: int = 256 * 2**20,
    ):
        self.ds, self.scene_dirs, self.weather, self.trajectory_frames = (
            ds,
            dict(scene_dirs),
            weather,
            trajectory_frames,
        )
        self._gauss: LRU[dict[str, torch.Tensor]] = LRU(items=capacity)
        self._derived: LRU[object] = LRU(items=capacity)
        self._images: LRU[np.ndarray] = LRU(nbytes=image_bytes, size=lambda img: img.nbytes)
        self._poses: dict[str, np.ndarray] = {}
        self._routes: dict[str, list] | None = None

    def derived(self, key: tuple, compute: Callable[[], T]) -> T:
        """``compute()``'s value, kept under ``key`` (LRU of ``capacity`` entries): for values that depend only on
        one frame's inputs of this store and on what ``key`` names besides (e.g. a selector's config)."""
        return self._derived.get(key, compute)  # type: ignore[return-value]

    def gaussians(self, scene: str, frame: int) -> dict[str, torch.Tensor]:
        """xyz/scale [N,3], rotation [N,4], opacity [N], code [N,C] of one frame (ego frame); the selector's path is
        ``selector_path``."""
        return self._gauss.get((scene, frame), lambda: self._read_gaussians(scene, frame))

    def _read_gaussians(self, scene: str, frame: int) -> dict[str, torch.Tensor]:
        path = gaussians_path(self.scene_dirs[scene], frame)
        arrays = gaussians_from_table(read_arrow(path, f"{scene}/frame_{frame:03d} distilled gaussians"))
        out = {
            k: torch.from_numpy(np.array(arrays[k], dtype=np.float32)) for k in ("xyz", "scale", "rotation", "opacity")
        }
        out["code"] = torch.from_numpy(np.array(arrays["feature"], dtype=np.float32))
        return out

    def selector_path(self, scene: str, frame: int, cfg: SelectorConfig) -> torch.Tensor:
        """[T, 2] ego path of the driving-aware selector at ``frame`` (``cfg.path``), in that frame's ego frame.

        Only the poses up to ``frame`` are read, and the route comes from the dataset (``routes.json``),
        so no recorded future pose reaches the selection (the leakage policy of ``PathSource``).
        """
        if scene not in self._poses:
            self._poses[scene] = self.ds.scene(scene).ego_poses
        known = self._poses[scene][: frame + 1]
        if cfg.path == PathSource.extrapolated:
            return torch.from_numpy(ego_trajectory_xy(known, frame, self.trajectory_frames))
        if self._routes is None:
            path = self.ds.root / ROUTES_FILE
            self._routes = json.loads(path.read_text()) if path.is_file() else {}
        if scene not in self._routes:
            raise DataError(
                f"{self.ds.root}: no planned route for {scene} ({ROUTES_FILE}), which model.selector.path=route "
                f"follows; rebuild the dataset with a builder that records routes (synthetic_mini does), or set "
                f"model.selector.path=extrapolated"
            )
        return torch.from_numpy(route_path(np.asarray(self._routes[scene]), known[frame], cfg.route_ahead_m))

    def images(self, sample: QASample) -> list[np.ndarray]:
        """The sample's camera views; none on a dataset without images (the GaussianDWM release): the LLM then reads
        the instruction and the world tokens only (rows that need images are refused before launch)."""
        if "images" not in self.ds.meta.get("tables", ["images"]):  # datasets built before tables were recorded
            return []
        return [self._image(sample.scene, sample.frame, cam) for cam in sample.views]

    def _image(self, scene: str, frame: int, cam: str) -> np.ndarray:
        """One decoded view, read-only (callers share it), from the LRU of ``image_bytes``."""

        def read() -> np.ndarray:
            img = self.ds.scene(scene).frame(frame).image(cam, self.weather)
            img.setflags(write=False)
            return img

        return self._images.get((scene, frame, cam), read)


def training_corpus(samples: Sequence[QASample]) -> list[str]:
    """Text the tiny flavor's BPE tokenizer is trained on: the training split's instructions and answers."""
    return [t for s in samples for t in (s.instruction, s.answer)]


def instruction_pairs(samples: Sequence[QASample]) -> list[tuple[str, str]]:
    """(instruction, answer) of the training split: the tiny flavor's warm-up with
    ``model.llm.pretrain_on=instructions`` (text only: never an image, a Gaussian or a val sample)."""
    return [(s.instruction, s.answer) for s in samples]
