"""Fréchet distances: the closed form, the names and protocols, and the errors without standard weights."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipelines.generation.frechet import (
    build_extractor,
    daisy_extractor,
    frechet,
    frechet_distance,
    fvd_extractor,
    inception_extractor,
)


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
    with pytest.raises(FileNotFoundError, match="FVD needs an I3D TorchScript file from a local path"):
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
