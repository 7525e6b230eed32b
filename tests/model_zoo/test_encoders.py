import json
import pickle

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from model_zoo import registry
from model_zoo.encoders import DaisyConfig, DaisyEncoder, QwenVisionConfig, QwenVisionEncoder, upsample_grid
from model_zoo.encoders.daisy import orthogonal_projection
from model_zoo.encoders.qwen3_vl_vision import EXPECTED_FILES, tiny_vision_config

H, W = 90, 160


def _textures() -> np.ndarray:
    """Left half diagonal stripes (3 px), right half a 4 px checker board."""
    yy, xx = np.mgrid[0:H, 0:W]
    stripes = ((xx + yy) // 3 % 2) * 200 + 25
    checker = ((xx // 4 + yy // 4) % 2) * 200 + 25
    gray = np.where(xx < W // 2, stripes, checker).astype(np.uint8)
    return np.repeat(gray[..., None], 3, axis=2)


def _noise(seed: int, h: int = H, w: int = W) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


@pytest.fixture(scope="module")
def daisy() -> DaisyEncoder:
    return registry.build("encoder", "daisy")


# ---------------------------------------------------------------- shared helpers


def test_upsample_grid_matches_interpolate_for_patch_tokens_and_hits_keypoints_exactly():
    g = torch.Generator().manual_seed(0)
    grid_hwC = torch.randn(3, 4, 5, generator=g)
    # 8x8 px patches: token centres at 3.5, 11.5, ... = align_corners=False convention
    ours = upsample_grid(grid_hwC, (24, 32), (3.5, 3.5), (8.0, 8.0))
    ref = F.interpolate(grid_hwC.permute(2, 0, 1)[None], size=(24, 32), mode="bilinear", align_corners=False)
    torch.testing.assert_close(ours, ref[0].permute(1, 2, 0))
    # keypoints on pixels 0, 4, 8: the map equals the grid there, and is the midpoint half-way
    keyed = upsample_grid(grid_hwC, (9, 13), (0.0, 0.0), (4.0, 4.0))
    torch.testing.assert_close(keyed[::4, ::4], grid_hwC)
    torch.testing.assert_close(keyed[2, 6], grid_hwC[:2, 1:3].mean(dim=(0, 1)))


def test_orthogonal_projection_is_orthonormal_and_seeded():
    p = orthogonal_projection(137, 64, seed=0)
    torch.testing.assert_close(p.T @ p, torch.eye(64), atol=1e-5, rtol=0)
    wide = orthogonal_projection(16, 64, seed=0)
    torch.testing.assert_close(wide @ wide.T, torch.eye(16), atol=1e-5, rtol=0)
    assert torch.equal(p, orthogonal_projection(137, 64, seed=0))
    assert not torch.equal(p, orthogonal_projection(137, 64, seed=1))


# ---------------------------------------------------------------- daisy


def test_daisy_shape_unit_norm_and_valid_border(daisy):
    f = daisy.encode(_noise(0))
    assert f.shape == (H, W, 64) and f.dtype == torch.float32
    valid = daisy.valid_mask(H, W)
    assert valid.shape == (H, W) and valid.dtype == torch.bool
    # radius 8, keypoints every 4 px: rows 8..80 and columns 8..148 interpolate keypoints >= 8 px inside
    rows, cols = valid.nonzero().unbind(1)
    assert (rows.min().item(), rows.max().item(), cols.min().item(), cols.max().item()) == (8, 80, 8, 148)
    assert valid.sum().item() == 73 * 141
    torch.testing.assert_close(f[valid].norm(dim=-1), torch.ones(73 * 141))
    # a flat image still has a defined (flatness) feature
    torch.testing.assert_close(
        daisy.encode(np.full((H, W, 3), 128, np.uint8))[valid].norm(dim=-1), torch.ones(73 * 141)
    )


def test_daisy_is_frozen_and_deterministic_byte_for_byte(daisy):
    img = _noise(1)
    a = daisy.encode(img).numpy().tobytes()
    assert a == daisy.encode(img).numpy().tobytes()
    assert a == registry.build("encoder", "daisy", DaisyConfig()).encode(torch.from_numpy(img)).numpy().tobytes()
    assert a == pickle.loads(pickle.dumps(daisy)).encode(img).numpy().tobytes()  # ships to Ray workers
    assert a != registry.build("encoder", "daisy", DaisyConfig(seed=1)).encode(img).numpy().tobytes()
    assert not any(p.requires_grad for p in daisy.parameters())
    daisy.train()
    assert not daisy.training


def test_daisy_different_images_give_different_features(daisy):
    valid = daisy.valid_mask(H, W)
    a, b, t = (daisy.encode(img)[valid] for img in (_noise(2), _noise(3), _textures()))
    # two draws of the same noise are the same texture: different bytes, similar descriptors
    assert (a - b).abs().mean().item() > 0.005
    same_texture = (a * b).sum(-1).mean().item()
    assert same_texture > 0.95
    # noise against stripes/checkers: clearly less similar
    assert (a * t).sum(-1).mean().item() < same_texture - 0.05


def test_daisy_is_informative_same_texture_closer_than_different_texture(daisy):
    f = daisy.encode(_textures())
    valid = daisy.valid_mask(H, W)
    left, right = valid.clone(), valid.clone()
    left[:, W // 2 - 8 :] = False  # keep the descriptor footprints on one texture each
    right[:, : W // 2 + 8] = False
    fl, fr = f[left], f[right]
    within = min((fl @ fl.T).mean().item(), (fr @ fr.T).mean().item())
    across = (fl @ fr.T).mean().item()
    print(f"mean cosine within {within:.3f}, across {across:.3f}")
    assert within > 0.99
    assert within - across > 0.1


def test_daisy_out_hw_and_input_errors(daisy):
    img = _noise(4)
    assert daisy.encode(img, out_hw=(45, 80)).shape == (45, 80, 64)
    assert daisy.valid_mask(H, W, out_hw=(45, 80)).shape == (45, 80)
    assert torch.equal(daisy.valid_mask(H, W, out_hw=(H, W)), daisy.valid_mask(H, W))
    with pytest.raises(ValueError) as e:
        daisy.encode(np.zeros((4, 4), np.uint8))
    assert str(e.value) == "daisy: expected an RGB image [H, W, 3] uint8, got shape [4, 4] dtype uint8"
    with pytest.raises(ValueError) as e:
        daisy.encode(torch.zeros(4, 4, 3))
    assert str(e.value) == "daisy: expected an RGB image [H, W, 3] uint8, got shape [4, 4, 3] dtype torch.float32"


def test_daisy_encode_views_stacks():
    enc = registry.build("encoder", "daisy", DaisyConfig(d_f=16, step=2, radius=4.0))
    views = np.stack([_noise(5, 24, 32), _noise(6, 24, 32)])
    out = enc.encode_views(views)
    assert out.shape == (2, 24, 32, 16)
    assert torch.equal(out[1], enc.encode(views[1]))


# ---------------------------------------------------------------- qwen3_vl_vision


@pytest.fixture(scope="module")
def qwen_tiny() -> QwenVisionEncoder:
    return registry.build("encoder", "qwen3_vl_vision", QwenVisionConfig(tiny=True))


def test_qwen_tiny_shape_grid_and_determinism(qwen_tiny):
    img = _noise(7, 48, 64)
    f = qwen_tiny.encode(img)
    assert f.shape == (48, 64, 32) and f.dtype == torch.float32
    assert qwen_tiny.d_f == 32
    assert f.numpy().tobytes() == qwen_tiny.encode(img).numpy().tobytes()
    other = registry.build("encoder", "qwen3_vl_vision", QwenVisionConfig(tiny=True))
    assert torch.equal(other.encode(img), f)  # seeded init
    # 8 px patches merged 2x2: one token per 16 px, each at the centre of its 16x16 block
    grid = qwen_tiny.token_grid(img)
    assert grid.shape == (3, 4, 32)
    torch.testing.assert_close(f[:8, :8], grid[0, 0].expand(8, 8, 32))  # up to the first centre (7.5): clamped
    # pixels 15 and 16 straddle the midpoint 15.5 between the first two centres
    torch.testing.assert_close(f[15:17, 15:17].mean(dim=(0, 1)), grid[:2, :2].mean(dim=(0, 1)))
    assert not any(p.requires_grad for p in qwen_tiny.parameters())
    assert torch.equal(qwen_tiny.valid_mask(48, 64), torch.ones(48, 64, dtype=torch.bool))


def test_qwen_hidden_tokens_are_in_raster_order():
    enc = registry.build("encoder", "qwen3_vl_vision", QwenVisionConfig(tiny=True, feature="hidden"))
    img = _noise(8, 48, 64)
    hidden = enc.token_grid(img)
    assert hidden.shape == (6, 8, 32)
    assert enc.encode(img).shape == (48, 64, 32)
    # the patch merger fuses each 2x2 window: merging our raster grid must give the tower's merged tokens
    windows = hidden.reshape(3, 2, 4, 2, 32).permute(0, 2, 1, 3, 4).reshape(12 * 4, 32)
    with torch.no_grad():
        merged = enc.model.merger(windows).reshape(3, 4, 32)
    torch.testing.assert_close(
        merged, registry.build("encoder", "qwen3_vl_vision", QwenVisionConfig(tiny=True)).token_grid(img)
    )


def test_qwen_save_pretrained_round_trip_through_the_path_loader(qwen_tiny, tmp_path):
    qwen_tiny.model.save_pretrained(tmp_path)
    qwen_tiny.processor.save_pretrained(tmp_path)
    loaded = registry.build("encoder", "qwen3_vl_vision", QwenVisionConfig(path=str(tmp_path)))
    img = _noise(9, 48, 64)
    assert loaded.encode(img).numpy().tobytes() == qwen_tiny.encode(img).numpy().tobytes()
    # without preprocessor_config.json the Qwen3-VL release defaults apply: mean = std = 0.5, >= 65536 pixels
    (tmp_path / "preprocessor_config.json").unlink()
    defaults = registry.build("encoder", "qwen3_vl_vision", QwenVisionConfig(path=str(tmp_path)))
    assert (tuple(defaults.processor.image_mean), tuple(defaults.processor.image_std)) == ((0.5,) * 3, (0.5,) * 3)
    # 48x64 upscaled to 224x304 (multiples of 16), 28x38 patches, 14x19 merged tokens
    assert defaults.token_grid(img).shape == (14, 19, 32)
    small = registry.build("encoder", "qwen3_vl_vision", QwenVisionConfig(path=str(tmp_path), min_pixels=4096))
    assert small.token_grid(img).shape == (4, 5, 32)


def test_qwen_loads_the_tower_out_of_a_sharded_full_checkpoint(tmp_path):
    from transformers.models.qwen3_vl import Qwen3VLConfig
    from transformers.models.qwen3_vl.modeling_qwen3_vl import Qwen3VLForConditionalGeneration

    text = {
        "vocab_size": 64,
        "hidden_size": 32,
        "intermediate_size": 64,
        "num_hidden_layers": 1,
        "num_attention_heads": 2,
        "num_key_value_heads": 1,
        "head_dim": 16,
        "rope_parameters": {"rope_type": "default", "rope_theta": 10000.0, "mrope_section": [2, 3, 3]},
    }
    full = Qwen3VLForConditionalGeneration(
        Qwen3VLConfig(vision_config=tiny_vision_config().to_dict(), text_config=text)
    )
    full.save_pretrained(tmp_path, max_shard_size="20KB")
    loaded = registry.build("encoder", "qwen3_vl_vision", QwenVisionConfig(path=str(tmp_path)))
    tower = full.model.visual.state_dict()
    assert all(torch.equal(v, tower[k]) for k, v in loaded.model.state_dict().items())
    index = json.loads((tmp_path / "model.safetensors.index.json").read_text())
    shard = tmp_path / index["weight_map"]["model.visual.patch_embed.proj.weight"]
    shard.unlink()
    with pytest.raises(FileNotFoundError) as e:
        registry.build("encoder", "qwen3_vl_vision", QwenVisionConfig(path=str(tmp_path)))
    assert str(e.value) == (
        f"qwen3_vl_vision: shard {shard} listed in {tmp_path / 'model.safetensors.index.json'} is missing"
    )


def test_qwen_missing_checkpoint_errors_name_the_directory_and_files(tmp_path):
    absent = tmp_path / "Qwen3-VL-8B-Instruct"
    with pytest.raises(FileNotFoundError) as e:
        registry.build("encoder", "qwen3_vl_vision", QwenVisionConfig(path=str(absent)))
    assert str(e.value) == (
        f"qwen3_vl_vision: checkpoint directory {absent} does not exist; expected config.json and model.safetensors "
        "(or model.safetensors.index.json with the shards it lists)"
    )
    absent.mkdir()
    (absent / "config.json").write_text(json.dumps({"model_type": "qwen3_vl"}))
    with pytest.raises(FileNotFoundError) as e:
        registry.build("encoder", "qwen3_vl_vision", QwenVisionConfig(path=str(absent)))
    assert str(e.value) == (
        f"qwen3_vl_vision: checkpoint directory {absent} lacks model.safetensors (or model.safetensors.index.json); "
        f"expected {EXPECTED_FILES}"
    )
    (absent / "config.json").unlink()
    with pytest.raises(FileNotFoundError) as e:
        registry.build("encoder", "qwen3_vl_vision", QwenVisionConfig(path=str(absent)))
    assert str(e.value).startswith(f"qwen3_vl_vision: checkpoint directory {absent} lacks config.json and model.")
    with pytest.raises(FileNotFoundError) as e:
        registry.build("encoder", "qwen3_vl_vision")
    assert str(e.value) == (
        "qwen3_vl_vision: no checkpoint directory given (QwenVisionConfig.path is None); expected a local directory "
        f"with {EXPECTED_FILES}, or tiny=True"
    )


def test_qwen_rejects_a_checkpoint_of_another_model(tmp_path):
    (tmp_path / "config.json").write_text(json.dumps({"model_type": "qwen2_5_vl"}))
    (tmp_path / "model.safetensors").write_bytes(b"")
    with pytest.raises(ValueError) as e:
        registry.build("encoder", "qwen3_vl_vision", QwenVisionConfig(path=str(tmp_path)))
    assert str(e.value) == (
        f"qwen3_vl_vision: {tmp_path / 'config.json'} has model_type 'qwen2_5_vl', not one of "
        "('qwen3_vl', 'qwen3_vl_moe', 'qwen3_vl_vision')"
    )


def test_qwen_bfloat16_tower_still_returns_float32_and_dtype_is_checked():
    enc = registry.build("encoder", "qwen3_vl_vision", QwenVisionConfig(tiny=True, dtype="bfloat16"))
    assert next(enc.model.parameters()).dtype == torch.bfloat16
    f = enc.encode(_noise(10, 48, 64))
    assert f.shape == (48, 64, 32) and f.dtype == torch.float32
    with pytest.raises(ValueError) as e:
        registry.build("encoder", "qwen3_vl_vision", QwenVisionConfig(tiny=True, dtype="bf16"))
    assert str(e.value) == "qwen3_vl_vision: dtype 'bf16' is not a torch floating-point dtype name"


# ---------------------------------------------------------------- langsplat_proxy (the Distillation ✗ arm)


def _blocks() -> np.ndarray:
    """Four flat colour quadrants: four regions, each one colour."""
    img = np.zeros((H, W, 3), np.uint8)
    img[: H // 2, : W // 2] = (200, 40, 40)
    img[: H // 2, W // 2 :] = (40, 200, 40)
    img[H // 2 :, : W // 2] = (40, 40, 200)
    img[H // 2 :, W // 2 :] = (220, 220, 220)
    return img


def test_langsplat_proxy_is_constant_per_region_and_unit_norm():
    enc = registry.build("encoder", "langsplat_proxy")
    feat = enc.encode(_blocks())
    assert feat.shape == (H, W, 64) and enc.valid_mask(H, W).all()
    torch.testing.assert_close(feat.norm(dim=-1), torch.ones(H, W))
    # inside each quadrant (the smoothed pixels on a colour edge form thin regions of their own)
    quads = [feat[2:43, 2:78], feat[2:43, 82:-2], feat[47:-2, 2:78], feat[47:-2, 82:-2]]
    for q in quads:  # a mask-level feature: one vector per region, as LangSplat's
        assert torch.equal(q, q[:1, :1].expand_as(q))
    assert len({tuple(q[0, 0].tolist()) for q in quads}) == 4
    smaller = enc.encode(_blocks(), out_hw=(9, 16))  # nearest: never a blend of two regions
    assert set(map(tuple, smaller.reshape(-1, 64).tolist())) <= set(map(tuple, feat.reshape(-1, 64).tolist()))


def test_langsplat_proxy_is_another_encoder_than_the_foundation_one(daisy):
    """The ablation's ✗ arm must not distil the ✓ arm's features: different maps of the same image, deterministic."""
    img = _noise(3)
    proxy = registry.build("encoder", "langsplat_proxy")
    a = proxy.encode(img)
    assert torch.equal(a, registry.build("encoder", "langsplat_proxy").encode(img))
    d = daisy.encode(img)
    assert a.shape == d.shape
    assert (F.cosine_similarity(a, d, dim=-1).abs() < 0.9).float().mean() > 0.95
    assert len(torch.unique(a.reshape(-1, 64), dim=0)) < H * W / 10  # regions, not pixels
    assert len(torch.unique(d.reshape(-1, 64), dim=0)) > H * W / 2
    pickle.loads(pickle.dumps(proxy))  # ships to Ray workers


def test_every_encoder_builds_from_the_pipeline_settings_taking_only_its_own_fields():
    """``EncoderSettings`` picks no variant: daisy takes d_f and the seed, the LangSplat stand-in d_f (its lift keeps
    seed 1), the Qwen tower the checkpoint path and the tiny flavor."""
    from model_zoo.encoders import EncoderSettings, LangSplatProxyConfig

    s = EncoderSettings(d_f=16, seed=5, path="/nonexistent", tiny=True)
    assert [n for _, n in registry.variants("encoder")] == ["daisy", "langsplat_proxy", "qwen3_vl_vision"]
    assert registry.build("encoder", "daisy", s).cfg == DaisyConfig(d_f=16, seed=5)
    assert registry.build("encoder", "langsplat_proxy", s).cfg == LangSplatProxyConfig(d_f=16, seed=1)
    qwen = registry.build("encoder", "qwen3_vl_vision", s)
    assert qwen.cfg == QwenVisionConfig(path="/nonexistent", tiny=True)
    assert qwen.d_f == tiny_vision_config().out_hidden_size
