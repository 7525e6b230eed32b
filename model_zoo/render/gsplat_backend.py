"""gsplat backend (CUDA): maps our inputs onto ``gsplat.rasterization`` and its outputs back.

Legend: N Gaussians, D value channels (colours then features), H x W image.
Differences from ``torch_tiles`` that parity tests tolerate: gsplat clamps per-pixel alpha at 0.999 (we: 0.99) and
stops compositing at T <= 1e-4 (we: T < 1e-4); with opacities below 0.99 the first never matters.
"""

from __future__ import annotations

from torch import Tensor

from model_zoo.render.camera import Camera
from model_zoo.render.project import Splatted


def splat_gsplat(
    means_N3: Tensor,
    scales_N3: Tensor,
    quats_N4: Tensor,
    opacities_N: Tensor,
    values_ND: Tensor,
    camera: Camera,
    tile_size: int,
    eps2d: float,
) -> Splatted:
    """Render with ``gsplat.rasterization`` (classic mode, unpacked, no background: ``rasterize`` adds it)."""
    try:
        import gsplat
    except ImportError as e:
        raise ImportError("the gsplat rasterizer backend needs the gsplat package (CUDA): pip install gdwm[gpu]") from e
    if not means_N3.is_cuda:
        raise ValueError(f"the gsplat backend needs CUDA tensors, got means on {means_N3.device}")
    # "RGB+D" gives sum_i w_i z_i as a last channel; rasterize() normalises it like every other backend. ("RGB+ED"
    # would divide by alpha clamped at 1e-10 first, and undoing that loses precision where alpha is small.)
    render_HWE, alpha_HW1, meta = gsplat.rasterization(
        means=means_N3,
        quats=quats_N4,
        scales=scales_N3,
        opacities=opacities_N,
        colors=values_ND,
        viewmats=camera.world2cam_44[None],
        Ks=camera.K_33[None],
        width=camera.width,
        height=camera.height,
        near_plane=camera.near,
        far_plane=camera.far,
        eps2d=eps2d,
        packed=False,
        tile_size=tile_size,
        backgrounds=None,
        render_mode="RGB+D",
        rasterize_mode="classic",
    )
    radii = meta["radii"][0]  # [N] before gsplat 1.5, [N, 2] (per axis) since
    n_visible = int((radii > 0).all(dim=-1).sum()) if radii.dim() == 2 else int((radii > 0).sum())
    render_HWE, alpha_HW = render_HWE[0], alpha_HW1[0, ..., 0]
    return Splatted(render_HWE[..., :-1], render_HWE[..., -1], alpha_HW, n_visible)
