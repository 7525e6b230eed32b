import re

import pytest
import torch

from model_zoo import registry
from model_zoo.diffusion import (
    DiffusionConfig,
    RGBDDual,
    add_noise,
    alphas_sigmas,
    depth_to_rgb,
    rgb_to_depth,
    v_target,
)
from model_zoo.diffusion.rgbd_dual import EXPECTED_LAYOUT

H, W = 48, 80
B = 2


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    """Tiny kernels gain nothing from 2 threads and stall badly when other jobs share the cores."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _batch(seed: int = 0) -> dict[str, torch.Tensor]:
    """Smooth RGB-D views (gradients plus a box), a half-valid sparse condition and a 5-token C_L."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, H), torch.linspace(0, 1, W), indexing="ij")

    def view() -> tuple[torch.Tensor, torch.Tensor]:
        phase = torch.rand(B, 3, 1, 1, generator=g)
        rgb = (0.5 + 0.4 * torch.sin(6.0 * xx + 3.0 * yy + 6.0 * phase)).clamp(0, 1)
        depth = 5.0 + 60.0 * yy.expand(B, H, W) * torch.rand(B, 1, 1, generator=g)
        return rgb, depth

    target_rgb, target_depth = view()
    ref_rgb, ref_depth = view()
    mask = (torch.rand(B, H, W, generator=g) > 0.5).float()
    return {
        "target_rgb": target_rgb,
        "target_depth": target_depth,
        "ref_rgb": ref_rgb,
        "ref_depth": ref_depth,
        "cond_rgb": target_rgb * mask[:, None],
        "cond_depth": target_depth * mask,
        "cond_mask": mask,
        "c_L_BLH": torch.randn(B, 5, 64, generator=g),
        "c_L_mask_BL": torch.tensor([[1.0] * 5, [1.0] * 3 + [0.0] * 2]),
    }


def _build(**kw) -> RGBDDual:
    return registry.build("diffusion", "rgbd_dual", DiffusionConfig(**kw))


def _loss(model: RGBDDual, batch: dict[str, torch.Tensor], seed: int = 7) -> float:
    with torch.no_grad():
        return model.loss(**batch, generator=torch.Generator().manual_seed(seed))[0].item()


def _sample(model: RGBDDual, batch: dict[str, torch.Tensor], **kw) -> tuple[torch.Tensor, torch.Tensor]:
    return model.sample(
        batch["ref_rgb"],
        batch["ref_depth"],
        batch["cond_rgb"],
        batch["cond_depth"],
        batch["cond_mask"],
        batch["c_L_BLH"],
        batch["c_L_mask_BL"],
        torch.Generator().manual_seed(3),
        steps=2,
        **kw,
    )


@pytest.fixture(scope="module")
def model() -> RGBDDual:
    return _build()


# ---------------------------------------------------------------------- pure math


def test_v_target_and_add_noise_closed_form():
    d = torch.tensor([[1.0, 2.0]])
    eps = torch.tensor([[3.0, -1.0]])
    torch.testing.assert_close(v_target(d, eps, 0.6, 0.8), torch.tensor([[1.0, -2.2]]))  # 0.6 eps - 0.8 d
    torch.testing.assert_close(add_noise(d, eps, 0.6, 0.8), torch.tensor([[3.0, 0.4]]))  # 0.6 d + 0.8 eps


def test_v_target_and_add_noise_equal_diffusers(model):
    g = torch.Generator().manual_seed(0)
    d = torch.randn(3, 8, 6, 10, generator=g)
    eps = torch.randn(3, 8, 6, 10, generator=g)
    t = torch.tensor([0, 500, 999])
    alpha, sigma = alphas_sigmas(model.scheduler, t)
    assert model.scheduler.config.prediction_type == "v_prediction"
    assert model.sample_scheduler.config.prediction_type == "v_prediction"
    torch.testing.assert_close(alpha**2 + sigma**2, torch.ones(3))
    torch.testing.assert_close(v_target(d, eps, alpha, sigma), model.scheduler.get_velocity(d, eps, t))
    torch.testing.assert_close(add_noise(d, eps, alpha, sigma), model.scheduler.add_noise(d, eps, t))


def test_depth_pseudo_rgb_round_trip():
    depth = torch.rand(2, H, W, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 80.0
    x = depth_to_rgb(depth, 80.0)
    assert x.shape == (2, 3, H, W) and x.dtype == torch.float64
    assert float(x.min()) >= -1.0 and float(x.max()) <= 1.0
    assert torch.equal(x[:, 0], x[:, 1]) and torch.equal(x[:, 0], x[:, 2])
    torch.testing.assert_close(rgb_to_depth(x, 80.0), depth, rtol=0, atol=1e-6)
    # float32 resolves 80 m only to ~8e-6 m: there the round trip holds to 1e-6 of max_depth
    x32 = depth_to_rgb(depth.float(), 80.0)
    torch.testing.assert_close(rgb_to_depth(x32, 80.0) / 80.0, depth.float() / 80.0, rtol=0, atol=1e-6)
    assert depth_to_rgb(torch.tensor([[[0.0, 40.0, 200.0]]]), 80.0)[0, :, 0].tolist() == [[-1.0, 0.0, 1.0]] * 3


# ---------------------------------------------------------------------- model


def test_registered_and_channel_layout(model):
    assert ("diffusion", "rgbd_dual") in registry.variants("diffusion")
    assert (model.unet.config.in_channels, model.unet.config.out_channels) == (6 * 4 + 1, 2 * 4)
    assert tuple(model.null_token.shape) == (1, 1, 64)
    assert not any(p.requires_grad for p in model.vae.parameters())
    assert model.rgbd_latent(torch.rand(1, 3, H, W), torch.rand(1, H, W)).shape == (1, 8, 24, 40)


@pytest.mark.parametrize(("low", "high"), [(True, False), (False, True), (True, True)])
def test_two_training_steps(low, high):
    model = _build(low_level=low, high_level=high).train()
    batch = _batch()
    unet0 = [p.detach().clone() for p in model.unet.parameters()]
    vae0 = [p.detach().clone() for p in model.vae.parameters()]
    opt = torch.optim.Adam(model.trainable_parameters(), lr=1e-3)
    g = torch.Generator().manual_seed(0)
    for _ in range(2):
        loss, parts = model.loss(**batch, generator=g)
        opt.zero_grad()
        loss.backward()
        opt.step()
        assert torch.isfinite(loss) and set(parts) == {"loss", "loss_rgb", "loss_depth"}
        assert parts["loss"] == pytest.approx((parts["loss_rgb"] + parts["loss_depth"]) / 2, rel=1e-5)
    assert any(not torch.equal(a, p) for a, p in zip(unet0, model.unet.parameters(), strict=True))
    assert all(torch.equal(a, p) for a, p in zip(vae0, model.vae.parameters(), strict=True))
    assert not model.vae.training


def test_high_level_off_ignores_c_L():
    batch = _batch()
    other = dict(batch, c_L_BLH=batch["c_L_BLH"] + 1.0)
    off = _build(high_level=False).train()
    assert _loss(off, batch) == _loss(off, other) == _loss(off, dict(batch, c_L_BLH=None, c_L_mask_BL=None))
    on = _build(high_level=True).train()
    assert _loss(on, batch) != _loss(on, other)


def test_low_level_off_ignores_c_I_c_D():
    batch = _batch()
    other = dict(batch, cond_rgb=batch["ref_rgb"], cond_depth=batch["ref_depth"], cond_mask=torch.ones(B, H, W))
    off = _build(low_level=False).train()
    assert _loss(off, batch) == _loss(off, other)
    on = _build(low_level=True).train()
    assert _loss(on, batch) != _loss(on, other)


def test_sample_shapes_and_cfg_uses_null_token(model):
    batch = _batch()
    rgb, depth = _sample(model, batch, guidance_scale=1.0)
    assert rgb.shape == (B, 3, H, W) and depth.shape == (B, H, W)
    assert torch.isfinite(rgb).all() and torch.isfinite(depth).all()
    assert 0.0 <= float(rgb.min()) <= float(rgb.max()) <= 1.0 and 0.0 <= float(depth.min()) <= float(depth.max()) <= 80
    rgb2, _ = _sample(model, batch, guidance_scale=2.0)
    assert float((rgb2 - rgb).abs().max()) > 1e-4
    off = _build(high_level=False)
    torch.testing.assert_close(_sample(off, batch, guidance_scale=1.0), _sample(off, batch, guidance_scale=2.0))


def test_fit_vae_reduces_reconstruction_loss():
    model = _build(vae_channels=(8, 16))
    batch = _batch()
    images = torch.cat([batch["target_rgb"], (depth_to_rgb(batch["target_depth"], 80.0) + 1) / 2])
    losses = model.fit_vae(images, steps=12, lr=3e-3, seed=0)
    assert len(losses) == 12
    assert losses[-1] < 0.8 * losses[0]
    assert not model.vae.training and not any(p.requires_grad for p in model.vae.parameters())
    with torch.no_grad():
        z = model.encode(images * 2 - 1)
    assert float(z.std()) == pytest.approx(1.0, rel=1e-3)  # scaling_factor re-estimated: unit-variance latents


def test_save_from_pretrained_round_trip(model, tmp_path):
    batch = _batch()
    model.save(tmp_path / "rgbd")
    assert sorted(p.name for p in (tmp_path / "rgbd").iterdir()) == ["null_token.pt", "rgbd.json", "unet", "vae"]
    loaded = RGBDDual.from_pretrained(tmp_path / "rgbd")
    assert loaded.cfg.image_size == (48, 80) and loaded.cfg.path == str(tmp_path / "rgbd")
    model.eval()
    assert _loss(loaded.eval(), batch) == _loss(model, batch)
    assert torch.equal(loaded.null_token, model.null_token)


def test_load_widens_a_pretrained_unet(tmp_path):
    """An SD-like UNet (in = out = L, another cross-attention width) gets zero input channels, a copied head, a proj."""
    from diffusers import UNet2DConditionModel

    torch.manual_seed(0)
    sd = UNet2DConditionModel(
        sample_size=(24, 40),
        in_channels=4,
        out_channels=4,
        down_block_types=("DownBlock2D", "CrossAttnDownBlock2D"),
        up_block_types=("CrossAttnUpBlock2D", "UpBlock2D"),
        block_out_channels=(32, 64),
        layers_per_block=1,
        cross_attention_dim=32,
        attention_head_dim=4,
        norm_num_groups=8,
    )
    sd.save_pretrained(tmp_path / "sd" / "unet")
    _build().vae.save_pretrained(tmp_path / "sd" / "vae")
    model = _build(tiny=False, path=str(tmp_path / "sd"))
    conv_in = model.unet.conv_in.weight
    assert conv_in.shape[1] == 25 and model.unet.config.in_channels == 25
    assert torch.equal(conv_in[:, :4], sd.conv_in.weight) and not conv_in[:, 4:].any()
    assert torch.equal(model.unet.conv_out.weight, sd.conv_out.weight.repeat(2, 1, 1, 1))
    assert model.unet.encoder_hid_proj.weight.shape == (32, 64)
    loss = _loss(model, _batch())
    assert torch.isfinite(torch.tensor(loss))
    model.save(tmp_path / "widened")  # the widened conv_in/conv_out and the C_L projection persist
    assert _loss(RGBDDual.from_pretrained(tmp_path / "widened"), _batch()) == loss


def test_missing_weights_are_clear_errors(tmp_path):
    with pytest.raises(FileNotFoundError) as err:
        _build(tiny=False)
    assert str(err.value) == f"diffusion/rgbd_dual: cfg.path is not set; full runs (tiny=False) need {EXPECTED_LAYOUT}"
    missing = tmp_path / "nope"
    with pytest.raises(FileNotFoundError) as err:
        _build(tiny=False, path=str(missing))
    assert (
        str(err.value) == f"diffusion/rgbd_dual: weight directory {missing} does not exist; expected {EXPECTED_LAYOUT}"
    )
    (tmp_path / "unet").mkdir()
    with pytest.raises(FileNotFoundError) as err:
        _build(tiny=False, path=str(tmp_path))
    assert str(err.value) == (
        f"diffusion/rgbd_dual: weight directory {tmp_path} lacks unet/ and vae/; expected {EXPECTED_LAYOUT}"
    )
    assert EXPECTED_LAYOUT == (
        "unet/ and vae/ subfolders in diffusers save_pretrained layout "
        "(config.json + diffusion_pytorch_model.safetensors)"
    )


def test_wrong_input_size_names_the_tensor(model):
    batch = dict(_batch(), ref_depth=torch.zeros(B, 32, 32))
    with pytest.raises(
        ValueError, match=re.escape("ref_depth must be [B, H, W] with (H, W) = (48, 80), got [2, 32, 32]")
    ):
        model.loss(**batch)
