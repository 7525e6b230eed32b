import math

import pytest
import torch

from model_zoo.quaternion import quat_to_rotmat
from model_zoo.render import rasterize
from model_zoo.render.project import ALPHA_MIN, covariance_3d, project_gaussians
from tests.model_zoo.render import pinhole


def test_rotmat_is_orthonormal_and_quaternion_scale_free():
    q = torch.randn(16, 4, dtype=torch.float64)
    R = quat_to_rotmat(q)
    torch.testing.assert_close(R @ R.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand(16, 3, 3))
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(16, dtype=torch.float64))
    torch.testing.assert_close(quat_to_rotmat(3.0 * q), R)


def test_covariance_rotated_90_degrees_about_z_swaps_x_and_y():
    s = torch.tensor([[1.0, 2.0, 3.0]], dtype=torch.float64)
    q = torch.tensor([[math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)]], dtype=torch.float64)
    torch.testing.assert_close(covariance_3d(s, q)[0], torch.diag(torch.tensor([4.0, 1.0, 9.0], dtype=torch.float64)))


def _analytic_alpha(cam, mean, s, o, eps2d):
    """o exp(-d^T Sigma'^-1 d / 2) with Sigma' = s^2 J J^T + eps2d I for an isotropic Gaussian, at pixel centres."""
    f, cx, cy = cam.K_33[0, 0].item(), cam.K_33[0, 2].item(), cam.K_33[1, 2].item()
    x, y, z = mean
    J = torch.tensor([[f / z, 0, -f * x / z**2], [0, f / z, -f * y / z**2]], dtype=torch.float64)
    cov = s**2 * J @ J.T + eps2d * torch.eye(2, dtype=torch.float64)
    mu = torch.tensor([f * x / z + cx, f * y / z + cy], dtype=torch.float64)
    vs, us = torch.meshgrid(torch.arange(cam.height), torch.arange(cam.width), indexing="ij")
    d = torch.stack([us, vs], dim=-1).double() + 0.5 - mu
    alpha = o * torch.exp(-0.5 * torch.einsum("hwi,ij,hwj->hw", d, torch.linalg.inv(cov), d))
    return torch.where(alpha >= ALPHA_MIN, alpha, torch.zeros_like(alpha)), mu


@pytest.mark.parametrize("backend", ["torch", "dense"])
def test_isotropic_gaussian_on_axis_renders_the_analytic_2d_gaussian(backend):
    cam = pinhole(16, 12, f=20.0, cx=7.3, cy=5.6, dtype=torch.float32)
    z, s, o, eps2d = 4.0, 0.5, 0.8, 0.3
    out = rasterize(
        torch.tensor([[0.0, 0.0, z]]), torch.full((1, 3), s), torch.tensor([[1.0, 0, 0, 0]]), torch.tensor([o]),
        torch.ones(1, 3), cam, backend=backend, tile_size=4, eps2d=eps2d,
    )  # fmt: skip
    # alpha(p) = o exp(-|p - mu|^2 / (2 s'^2)), s'^2 = (f s / z)^2 + eps2d, mu = (cx, cy).
    s2 = (20.0 * s / z) ** 2 + eps2d
    vs, us = torch.meshgrid(torch.arange(12), torch.arange(16), indexing="ij")
    r2 = (us + 0.5 - 7.3) ** 2 + (vs + 0.5 - 5.6) ** 2
    expected = o * torch.exp(-0.5 * r2 / s2)
    expected = torch.where(expected >= ALPHA_MIN, expected, torch.zeros_like(expected))
    torch.testing.assert_close(out.alpha, expected, atol=1e-5, rtol=0)
    assert out.alpha.argmax().item() == 5 * 16 + 7  # the pixel that contains (cx, cy) = (7.3, 5.6)
    torch.testing.assert_close(out.depth[out.alpha > 0], torch.full_like(out.depth[out.alpha > 0], z))


@pytest.mark.parametrize("backend", ["torch", "dense"])
def test_off_axis_gaussian_lands_at_its_projection_with_the_ewa_jacobian(backend):
    cam = pinhole(24, 20, f=20.0, cx=12.0, cy=10.0)
    mean, s, o = (1.1, -0.7, 3.0), 0.3, 0.7
    out = rasterize(
        torch.tensor([mean], dtype=torch.float64), torch.full((1, 3), s, dtype=torch.float64),
        torch.tensor([[0.3, -0.2, 0.9, 0.1]], dtype=torch.float64), torch.tensor([o], dtype=torch.float64),
        torch.ones(1, 3, dtype=torch.float64), cam, backend=backend, tile_size=8,
    )  # fmt: skip
    expected, mu = _analytic_alpha(cam, mean, s, o, 0.3)
    assert mu.tolist() == pytest.approx([12.0 + 20 * 1.1 / 3, 10.0 - 20 * 0.7 / 3])
    torch.testing.assert_close(out.alpha, expected, atol=1e-10, rtol=0)
    assert divmod(out.alpha.argmax().item(), 24) == (int(mu[1]), int(mu[0]))


def test_footprint_box_is_clipped_to_the_image_and_culling_flags():
    cam = pinhole(32, 24, f=30.0)
    means = torch.tensor(
        [[0.0, 0.0, 4.0], [0.0, 0.0, -4.0], [0.0, 0.0, 0.01], [0.0, 0.0, 2000.0], [50.0, 0.0, 4.0], [0.0, 0.0, 4.0]],
        dtype=torch.float64,
    )
    n = means.shape[0]
    opac = torch.tensor([0.5, 0.5, 0.5, 0.5, 0.5, 0.5 * ALPHA_MIN], dtype=torch.float64)
    p = project_gaussians(
        means, torch.full((n, 3), 0.1, dtype=torch.float64), torch.tensor([[1.0, 0, 0, 0]] * n, dtype=torch.float64),
        opac, cam, eps2d=0.3,
    )  # fmt: skip
    # In front / behind / before near / beyond far / off to the side / too transparent to ever reach ALPHA_MIN.
    assert p.valid_N.tolist() == [True, False, False, False, True, False]
    assert p.visible_N.tolist() == [True, False, False, False, False, False]
    # sigma' = sqrt((30 * 0.1 / 4)^2 + 0.3) px, reach sqrt(2 ln(0.5 * 255)) sigmas around (16, 12).
    reach = math.sqrt(2 * math.log(0.5 / ALPHA_MIN)) * math.sqrt((30 * 0.1 / 4) ** 2 + 0.3)
    lo, hi = math.ceil(16 - reach - 0.5), math.floor(16 + reach - 0.5)
    assert p.box_N4[0].tolist() == [lo, hi, math.ceil(12 - reach - 0.5), math.floor(12 + reach - 0.5)]
