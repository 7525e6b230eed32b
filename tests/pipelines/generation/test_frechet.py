"""Fréchet distances: the closed form, the names and protocols, and the errors without standard weights."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipelines.generation.frechet import (
    Extractor,
    build_extractor,
    build_video_extractor,
    daisy_extractor,
    frechet,
    frechet_distance,
    fvd_extractor,
    inception_extractor,
    label,
)
from pipelines.generation.metrics import clips, score_views
from pipelines.generation.samples import GenExample, GenTarget


def test_frechet_distance_equals_the_diagonal_closed_form():
    mu1, mu2 = np.array([0.0, 1.0, 2.0]), np.array([1.0, 1.0, 0.0])
    s1, s2 = np.array([1.0, 4.0, 9.0]), np.array([4.0, 1.0, 1.0])
    expected = ((mu1 - mu2) ** 2).sum() + (s1 + s2 - 2 * np.sqrt(s1 * s2)).sum()  # 5 + (1 + 1 + 4)
    assert frechet_distance(mu1, np.diag(s1), mu2, np.diag(s2)) == pytest.approx(expected) == pytest.approx(11.0)
    rng = np.random.default_rng(0)
    a = rng.normal(size=(50, 4))
    cov = np.cov(a, rowvar=False)
    assert frechet_distance(a.mean(0), cov, a.mean(0), cov) == pytest.approx(0.0, abs=1e-8)


def test_fd_with_daisy_is_named_approximate_and_grows_with_the_difference():
    ex = daisy_extractor(d_f=8)
    assert (ex.name, ex.protocol) == ("fd_daisy", "approximate")
    g = torch.Generator().manual_seed(0)
    real = torch.rand(6, 3, 24, 40, generator=g)
    near = (real + 0.02 * torch.randn(real.shape, generator=g)).clamp(0, 1)
    far = torch.zeros_like(real) + 0.5
    assert frechet(real, near, ex) < frechet(real, far, ex)


def test_fid_and_fvd_need_their_standard_weights_from_a_local_path(tmp_path):
    with pytest.raises(FileNotFoundError, match="FID needs the standard Inception weights as a TorchScript file"):
        inception_extractor(tmp_path / "pt_inception.pt")
    with pytest.raises(FileNotFoundError, match="FID needs the standard Inception TorchScript file"):
        build_extractor("inception")
    with pytest.raises(FileNotFoundError, match=r"FVD needs the I3D TorchScript file i3d_torchscript\.pt from a local"):
        fvd_extractor(None)
    with pytest.raises(ValueError, match="unknown Fréchet feature extractor 'clip'"):
        build_extractor("clip")


@pytest.mark.filterwarnings("ignore:`torch.jit.:DeprecationWarning")
def test_a_torchscript_inception_file_gives_fid(tmp_path):
    class Pool(torch.nn.Module):  # stands in for the exported network's interface: uint8 images -> features
        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return x.float().mean(dim=(2, 3))

    path = tmp_path / "inception.pt"
    torch.jit.script(Pool()).save(str(path))
    ex = inception_extractor(path)
    assert (ex.name, ex.protocol, ex.source) == ("fid", "official", str(path))
    imgs = torch.rand(4, 3, 8, 8)
    assert ex(imgs).shape == (4, 3)


# ----------------------------------------------------------------------------- Tab. world: pooled ±1 m, FVD


def _feature_extractor(name: str) -> Extractor:
    """Fixture features: an image's per-channel means (a video's: over frames too), so the reference is exact."""

    def run(x: torch.Tensor) -> np.ndarray:
        dims = (*range(1, x.ndim - 3), x.ndim - 2, x.ndim - 1)
        return x.double().mean(dim=dims).numpy()

    return Extractor(name, "approximate", "channel means", run)


def _reference_fd(real_ND: np.ndarray, fake_ND: np.ndarray) -> float:
    """The Fréchet distance by another route: Tr((C1 C2)^1/2) as the sum of sqrt of the eigenvalues of C1 C2."""
    m1, m2 = real_ND.mean(0), fake_ND.mean(0)
    c1, c2 = np.cov(real_ND, rowvar=False), np.cov(fake_ND, rowvar=False)
    ev = np.linalg.eigvals(c1 @ c2)
    return float(((m1 - m2) ** 2).sum() + np.trace(c1) + np.trace(c2) - 2 * np.sqrt(np.clip(ev.real, 0, None)).sum())


def _scored(frames: int = 4) -> list:
    """(example, generated rgb, depth) of scene s, frames 0..frames-1, at +1 m, -1 m and +2 m: random views."""
    g = torch.Generator().manual_seed(0)
    out = []
    for lateral in (1.0, -1.0, 2.0):
        for f in range(frames):
            t = GenTarget("s", f, "CAM_FRONT", "shift", lateral_m=lateral)
            real, fake = torch.rand(3, 6, 8, generator=g), torch.rand(3, 6, 8, generator=g) * 0.8
            depth = torch.full((6, 8), 10.0)
            out.append((GenExample(t, real, depth, real, depth, real, depth, torch.ones(6, 8)), fake, depth))
    return out


def test_pooled_pm1m_frechet_equals_a_reference_over_both_signs_views():
    scored = _scored(frames=5)
    ex = _feature_extractor("fd_means")
    s = score_views(scored, extractor=ex)
    pooled = [(e.target_rgb, r) for e, r, _ in scored if e.target.name in ("shift_1m", "shift_-1m")]
    real = np.stack([x.double().mean(dim=(1, 2)).numpy() for x, _ in pooled])
    fake = np.stack([y.double().mean(dim=(1, 2)).numpy() for _, y in pooled])
    assert len(real) == 10
    assert s["gen/shift_pm1m/fd_means"] == pytest.approx(_reference_fd(real, fake), rel=1e-6)
    assert s["gen/shift_pm1m/fd_means"] != pytest.approx(s["gen/shift_1m/fd_means"], rel=1e-3)
    assert "gen/shift_pm2m/fd_means" not in s  # only +2 m was generated: no ±2 m pool


def test_pooled_fvd_is_over_clips_of_consecutive_frames_of_both_signs():
    scored = _scored(frames=4)
    ex = _feature_extractor("fvd")
    s = score_views(scored, video_extractor=ex, clip_frames=2)
    # per sign: frames 0-1 and 2-3, so 4 clips in the ±1 m pool; a clip's feature = its channel means over 2 frames
    clip_ids = clips(scored, ["shift_1m", "shift_-1m"], 2)
    assert [[scored[i][0].target.frame for i in c] for c in clip_ids] == [[0, 1], [2, 3], [0, 1], [2, 3]]
    real = np.stack([torch.stack([scored[i][0].target_rgb for i in c]).double().mean(dim=(0, 2, 3)).numpy()
                     for c in clip_ids])  # fmt: skip
    fake = np.stack([torch.stack([scored[i][1] for i in c]).double().mean(dim=(0, 2, 3)).numpy() for c in clip_ids])
    assert s["gen/shift_pm1m/fvd"] == pytest.approx(_reference_fd(real, fake), rel=1e-6)


def test_a_missing_i3d_file_is_an_error_naming_the_path(tmp_path):
    path = tmp_path / "weights" / "i3d_torchscript.pt"
    with pytest.raises(FileNotFoundError) as e:
        build_video_extractor(str(path))
    assert str(e.value) == (
        f"FVD needs the I3D TorchScript file i3d_torchscript.pt; stage.evaluate_gen.fvd_weights={path} does not "
        "exist (place the StyleGAN-V i3d_torchscript.pt export there; it is never downloaded)"
    )


@pytest.mark.filterwarnings("ignore:`torch.jit.:DeprecationWarning")
def test_a_local_i3d_file_gives_fvd_with_the_stylegan_v_call(tmp_path):
    class I3D(torch.nn.Module):  # the export's interface: uint8 [N, 3, T, H, W] and three flags -> features
        def forward(self, x: torch.Tensor, rescale: bool, resize: bool, return_features: bool) -> torch.Tensor:
            assert x.dtype == torch.uint8 and rescale and resize and return_features
            return x.float().mean(dim=(2, 3, 4))

    path = tmp_path / "i3d_torchscript.pt"
    torch.jit.script(I3D()).save(str(path))
    ex = build_video_extractor(str(path))
    assert (ex.name, ex.protocol, ex.source) == ("fvd", "official", str(path))
    videos = torch.rand(3, 4, 3, 8, 8)  # [N, T, 3, H, W]
    np.testing.assert_allclose(ex(videos), (videos * 255).round().mean(dim=(1, 3, 4)).numpy(), rtol=1e-5)


def test_without_i3d_the_stand_in_is_labelled_and_never_called_fvd():
    ex = build_video_extractor(None)
    assert ex.name == "fd_video_daisy" and ex.protocol == "approximate"
    assert label(ex).startswith("fd_video_daisy: approximate (stand-in for FVD (no I3D weights): daisy")
    g = torch.Generator().manual_seed(0)
    clip = torch.rand(1, 3, 3, 24, 40, generator=g)
    still = clip[:, :1].expand(1, 3, 3, 24, 40)
    f_clip, f_still = ex(clip), ex(still)
    assert f_clip.shape == (1, 256)
    assert np.abs(f_still[:, 128:]).max() == 0.0 and np.abs(f_clip[:, 128:]).max() > 0  # temporal change counts
    s = score_views(_scored(frames=2), video_extractor=ex, clip_frames=2)
    # one clip per target: no per-target distance; the ±1 m pool has two clips
    assert {k for k in s if "video" in k or "fvd" in k} == {"gen/shift_pm1m/fd_video_daisy"}


def test_a_one_frame_clip_is_an_error_naming_the_key():
    with pytest.raises(ValueError, match=r"stage\.evaluate_gen\.fvd_clip_frames must be >= 2 \(a clip is a video\)"):
        score_views(_scored(frames=2), video_extractor=_feature_extractor("fvd"), clip_frames=1)
