"""Generation examples from the release's world samples: conditions equal to the resized pseudo frames, targets equal
to the ground truth, skips by reason, the latent pack checked but not read, exact errors."""

from __future__ import annotations

import json
import re

import cv2
import numpy as np
import pytest
import torch

from model_zoo.diffusion.vpred import depth_to_rgb
from pipelines.data.layout import DataError
from pipelines.data.reader import GSQADataset, WorldSample
from pipelines.generation.metrics import clips, score_views
from pipelines.generation.samples import GenExample
from pipelines.generation.world import (
    KIND,
    WorldTarget,
    check_latents,
    clip_conditions,
    split_samples,
    vae_images,
    world_clips,
)
from tests.pipelines.data.fixtures_release import PACK_SHAPE
from tests.pipelines.generation.conftest import import_release

HW = (16, 24)


def _area(img_HW3: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(cv2.resize(img_HW3, (HW[1], HW[0]), interpolation=cv2.INTER_AREA)).permute(2, 0, 1) / 255


def _nearest(d_HW: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(cv2.resize(d_HW, (HW[1], HW[0]), interpolation=cv2.INTER_NEAREST))


def _source(rel: str) -> str:
    """The fixture's path of an imported file (``release/<source-relative>``)."""
    return rel.removeprefix("release/")


def test_every_frame_of_a_sample_with_ground_truth_is_one_example(release_world):
    found, skipped = world_clips(release_world.ds, "train", release_world.distilled, HW, need_depth=True)
    assert dict(skipped) == {"no_ground_truth": 1}  # w2 has no ground-truth frames
    [clip] = found
    w, written = clip.sample, release_world.release
    assert (w.id, w.split, len(clip.examples)) == ("w1", "train", 3)
    ref = _area(written.images["images/world_ref.png"])
    for t, ex in enumerate(clip.examples):
        assert ex.target == WorldTarget("w1", "train", "scene_0000", 0, t, "CAM_FRONT")
        assert (ex.target.name, ex.target.clip) == (KIND, (("w1", "train"), t))
        assert tuple(ex.cond_rgb.shape) == tuple(ex.target_rgb.shape) == tuple(ex.ref_rgb.shape) == (3, *HW)
        assert tuple(ex.cond_depth.shape) == tuple(ex.target_depth.shape) == tuple(ex.cond_mask.shape) == HW
        torch.testing.assert_close(ex.ref_rgb, ref, rtol=0, atol=0)
        assert torch.equal(ex.ref_depth, torch.zeros(HW))  # the release has no depth of the reference view
        pseudo = _source(w.row["pseudo_rgb"][t])
        torch.testing.assert_close(ex.cond_rgb, _area(written.images[pseudo]), rtol=0, atol=0)
        depth = _nearest(written.depths[_source(w.row["pseudo_depth"][t])])
        assert torch.equal(ex.cond_depth, depth)
        assert torch.equal(ex.cond_mask, (depth > 0).float())
        torch.testing.assert_close(ex.target_rgb, _area(written.images[f"images/world_gt_{t:03d}.png"]), rtol=0, atol=0)
        assert torch.equal(ex.target_depth, _nearest(written.depths[f"depth/world_gt_{t:03d}.npz"]))
    assert clip.prompt.instruction == "<gauss>Generate the next 3 frames."
    p = clip.prompt
    assert (p.sample_id, p.scene, p.frame, p.task, p.views) == ("w1", "scene_0000", 0, KIND, ("CAM_FRONT",))


def _drop_w1_gt_depth(release) -> None:
    for name in ("world_train.jsonl", "world_val.jsonl"):
        path = release.root / name
        recs = [json.loads(line) for line in path.read_text().splitlines()]
        del recs[0]["gt_depth_npz_paths"]
        path.write_text("".join(json.dumps(r) + "\n" for r in recs))


@pytest.mark.filterwarnings("ignore:Mean of empty slice:RuntimeWarning")
def test_a_sample_without_ground_truth_depth_is_scored_without_depth_and_never_trained_on(tmp_path):
    imported = import_release(tmp_path, edit=_drop_w1_gt_depth)
    ds = imported.ds
    train, skipped = world_clips(ds, "train", imported.distilled, HW, need_depth=True)
    assert train == [] and dict(skipped) == {"no_gt_depth": 1, "no_ground_truth": 1}
    [val], skipped = world_clips(ds, "val", imported.distilled, HW, need_depth=False)
    assert not skipped and all(torch.equal(e.target_depth, torch.zeros(HW)) for e in val.examples)
    rgb = torch.stack([e.target_rgb for e in val.examples])
    scores = score_views([(e, rgb[i], torch.full(HW, 5.0)) for i, e in enumerate(val.examples)])
    assert scores[f"gen/{KIND}/psnr"] == float("inf") and scores[f"gen/{KIND}/ssim"] == pytest.approx(1.0)
    assert np.isnan(scores[f"gen/{KIND}/depth_absrel"])  # no valid ground-truth pixel anywhere


def test_samples_without_gaussians_are_skipped_by_reason(release_world, tmp_path):
    ds = release_world.ds
    only_other_scene = {"scene_0002": release_world.distilled["scene_0002"]}
    assert dict(world_clips(ds, "val", only_other_scene, HW, need_depth=False)[1]) == {"scene_without_gaussians": 1}
    lacking = tmp_path / "scene_0000"
    (lacking / "gaussians").mkdir(parents=True)
    assert dict(world_clips(ds, "val", {"scene_0000": lacking}, HW, need_depth=False)[1]) == {
        "frame_without_gaussians": 1
    }


def test_the_latent_pack_is_checked_from_its_meta_and_never_used_as_a_target(release_world):
    ds = release_world.ds
    w1, w2 = split_samples(ds, "train")
    assert check_latents(w1) == check_latents(w2) == PACK_SHAPE[1:]
    row = dict(w1.row, latent_indices=[1, 2, 5])
    with pytest.raises(DataError, match=re.escape("world sample 'w1' (train): latent_indices reach 5 but ")):
        check_latents(WorldSample(ds, row))
    with pytest.raises(DataError, match=re.escape("world sample 'w1' (train): 2 latent_indices for 3 pseudo frames")):
        check_latents(WorldSample(ds, dict(w1.row, latent_indices=[1, 2])))


def test_a_split_without_world_samples_is_an_error_naming_dataset_and_split(release_world, synth_small):
    ds = release_world.ds
    with pytest.raises(DataError) as e:
        split_samples(ds, "test")
    assert str(e.value) == (
        f"dataset 'gaussiandwm_release' at {ds.root}: no world samples in split 'test'; "
        "its world table holds splits ['train', 'val']"
    )
    synth = GSQADataset(synth_small)
    with pytest.raises(DataError, match=re.escape(f"at {synth.root}: no world samples in split 'train'; it has no ")):
        world_clips(synth, "train", {}, HW, need_depth=True)


def test_vae_images_are_references_and_drawn_ground_truth_frames_with_their_depth(release_world):
    ds = release_world.ds
    samples = split_samples(ds, "train")
    x = vae_images(samples, HW, 80.0, frames_per_sample=2, seed=0)
    # w1: reference + 2 frames (rgb, depth); w2: its reference only (no ground truth)
    assert tuple(x.shape) == (6, 3, *HW) and float(x.min()) >= 0.0 and float(x.max()) <= 1.0
    written = release_world.release.images
    assert torch.equal(x[0], _area(written["images/world_ref.png"]).float())
    assert torch.equal(x[5], _area(written["images/w2_ref.png"]).float())
    gt = [_area(written[f"images/world_gt_{t:03d}.png"]).float() for t in range(3)]
    drawn = [t for t in range(3) if any(torch.equal(x[k], gt[t]) for k in (1, 3))]
    assert len(drawn) == 2
    depth = _nearest(release_world.release.depths[f"depth/world_gt_{drawn[0]:03d}.npz"])
    torch.testing.assert_close(x[2], (depth_to_rgb(depth[None], 80.0)[0] + 1) / 2)


def test_without_the_high_level_condition_every_example_gets_none(release_world):
    found, _ = world_clips(release_world.ds, "val", release_world.distilled, HW, need_depth=False)
    assert clip_conditions(None, release_world.ds, release_world.distilled, found, 4) == [None, None, None]


def test_each_world_sample_is_a_clip_of_its_own_for_the_video_distance():
    def ex(sample: str, t: int) -> GenExample:
        z = torch.zeros(2, 2)
        target = WorldTarget(sample, "val", "scene_0000", 0, t, "CAM_FRONT")
        return GenExample(target, torch.zeros(3, 2, 2), z, torch.zeros(3, 2, 2), z, torch.zeros(3, 2, 2), z, z)

    # two samples of one scene, frame and camera, interleaved: a (scene, camera) key would merge them
    scored = [(ex(s, t), None, None) for t in range(3) for s in ("a", "b")]
    assert clips(scored, [KIND], 3) == [[0, 2, 4], [1, 3, 5]]
    assert clips(scored, [KIND], 2) == [[0, 2], [1, 3]]
