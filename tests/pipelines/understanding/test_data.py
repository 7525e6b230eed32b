"""QA samples, task-aware sampling and the ego-trajectory prior."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from pipelines.data.layout import DataError
from pipelines.data.reader import GSQADataset
from pipelines.understanding.data import (
    FrameStore,
    QASample,
    TaskSampler,
    balanced_subset,
    ego_trajectory_xy,
    load_samples,
    task_probabilities,
)


def test_task_probabilities_follow_eq_p_m():
    p = task_probabilities({"rdp": 100, "plan": 25, "traj": 0}, alpha=0.5)
    assert p == pytest.approx({"rdp": 10 / 15, "plan": 5 / 15})  # sqrt(100)=10, sqrt(25)=5; empty tasks drop out
    assert task_probabilities({"a": 30, "b": 10}, alpha=1.0) == pytest.approx({"a": 0.75, "b": 0.25})
    assert task_probabilities({"a": 30, "b": 10}, alpha=0.0) == pytest.approx({"a": 0.5, "b": 0.5})


def _samples(counts: dict[str, int]) -> list[QASample]:
    return [QASample(f"s/{t}/{i}", "s", 0, t, "q <gauss>", "a", ()) for t, n in counts.items() for i in range(n)]


def test_task_sampler_is_deterministic_per_step_and_balances_tasks():
    samples = _samples({"big": 900, "small": 100})
    sampler = TaskSampler(samples, alpha=0.0, seed=3)
    assert sampler.batch(7, 16) == sampler.batch(7, 16)  # a resumed run draws the same batch at step 7
    assert sampler.batch(7, 16) != sampler.batch(8, 16)
    drawn = Counter(samples[i].task for step in range(200) for i in sampler.batch(step, 10))
    assert 0.45 < drawn["small"] / 2000 < 0.55  # alpha_s = 0: uniform over tasks despite 9:1 sizes
    with pytest.raises(DataError, match="no training samples"):
        TaskSampler([], 0.5, 0)


def test_balanced_subset_shares_the_budget_across_families_and_frames():
    """evaluate_qa's max_samples: the first N of the split were the first frames of one scene (no plan, no traj)."""
    order = [("rdp", 30), ("vg2d", 30), ("vg3d", 30), ("plan", 6), ("traj", 2)]
    samples = [QASample(f"{t}/{i}", "s", i, t, "q", "a", ()) for t, n in order for i in range(n)]
    sub = balanced_subset(samples, 20)
    # round robin in the split's family order; traj gives what it lacks to the others
    assert Counter(s.task for s in sub) == {"rdp": 5, "vg2d": 5, "vg3d": 4, "plan": 4, "traj": 2}
    assert [s.frame for s in sub if s.task == "rdp"] == [0, 6, 12, 18, 24]  # spread over the family's samples
    assert sub == sorted(sub, key=samples.index)  # the split's order (ranking-based mAP reads it)
    assert Counter(s.task for s in balanced_subset(samples, 50)) == {"rdp": 14, "vg2d": 14, "vg3d": 14, "plan": 6,
                                                                      "traj": 2}  # fmt: skip
    assert balanced_subset(samples, 0) == samples and balanced_subset(samples, 500) == samples
    assert balanced_subset(samples, 3) == balanced_subset(samples, 3)


def test_ego_trajectory_prior_uses_the_past_and_extrapolates():
    poses = np.repeat(np.eye(4)[None], 10, axis=0)
    poses[:, 0, 3] = np.arange(10) * 2.0  # driving +x at 2 m per frame
    traj = ego_trajectory_xy(poses, frame=5, frames=3)
    np.testing.assert_allclose(traj[:, 0], [-6, -4, -2, 0, 2, 4, 6])
    np.testing.assert_allclose(traj[:, 1], 0)
    assert ego_trajectory_xy(poses, frame=0, frames=3).tolist() == [[0, 0]] * 4  # no history: stand still


def test_load_samples_counts_what_it_skips(synth_small, tmp_path):
    ds = GSQADataset(synth_small)
    all_train = ds.qa(split="train").num_rows
    scene = ds.scene_ids[0]
    (tmp_path / scene / "gaussians").mkdir(parents=True)
    (tmp_path / scene / "gaussians" / "00000.arrow").write_bytes(b"")
    samples, skipped = load_samples(ds, "train", {scene: tmp_path / scene}, need_gaussians=True)
    assert all(s.scene == scene and s.frame == 0 for s in samples) and samples
    with_gauss = [s for s in samples if "<gauss>" in s.instruction]
    assert len(with_gauss) == len(samples)
    assert sum(skipped.values()) + len(samples) == all_train
    assert skipped["frame_excluded_by_qc"] > 0
    free, none_skipped = load_samples(ds, "train", {}, need_gaussians=False)
    assert len(free) == all_train and not none_skipped


def test_frame_store_decodes_a_view_once_read_only_within_its_byte_budget(synth_small, monkeypatch):
    from pipelines.data import reader

    ds = GSQADataset(synth_small)
    samples, _ = load_samples(ds, "train", {}, need_gaussians=False)
    a = next(s for s in samples if len(s.views) >= 2)
    b = next(s for s in samples if (s.scene, s.frame) != (a.scene, a.frame) and s.views)
    reads = []
    image = reader.Frame.image
    monkeypatch.setattr(reader.Frame, "image", lambda f, cam, w="clear": reads.append((f.idx, cam)) or image(f, cam, w))
    one = ds.scene(a.scene).frame(a.frame).image(a.views[0], "clear")
    store = FrameStore(ds, {}, "clear", 3, image_bytes=len(a.views) * one.nbytes)
    first = store.images(a)
    direct = [ds.scene(a.scene).frame(a.frame).image(c, "clear") for c in a.views]
    assert len(first) == len(a.views) and all(np.array_equal(x, y) for x, y in zip(first, direct, strict=True))
    assert all(not x.flags.writeable for x in first)
    reads.clear()
    assert all(x is y for x, y in zip(store.images(a), first, strict=True)) and reads == []  # kept
    store.images(b)  # over the budget: a's views go first
    store.images(a)
    assert reads[-len(a.views) :] == [(a.frame, c) for c in a.views]
    computed = []
    assert store.derived(("k", 1), lambda: computed.append(1) or "v") == "v"
    assert store.derived(("k", 1), lambda: computed.append(2) or "w") == "v" and computed == [1]
