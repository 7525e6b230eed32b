"""3DGS optimisation of one scene on its training views, with densification, pruning and opacity reset.

Legend: N Gaussians. Parameters live in activation-free form (log-scales, opacity logits, colour logits).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from model_zoo.quaternion import quat_mul, quat_to_rotmat
from model_zoo.render import Camera, rasterize
from pipelines.data.layout import matrix_to_quat_wxyz
from pipelines.recon.config import ReconstructConfig
from pipelines.recon.init import View
from pipelines.recon.losses import photometric, psnr, ssim


class NaNLossError(FloatingPointError):
    pass


@dataclass
class Gaussians:
    means: torch.Tensor  # [N, 3] world (static) or box frame (dynamic)
    log_scales: torch.Tensor  # [N, 3]
    quats: torch.Tensor  # [N, 4] wxyz, unnormalised
    opacity_logits: torch.Tensor  # [N]
    color_logits: torch.Tensor  # [N, 3]
    instance: torch.Tensor  # [N] long: index into the moving instances, -1 = static

    def params(self) -> dict[str, torch.Tensor]:
        return {k: getattr(self, k) for k in ("means", "log_scales", "quats", "opacity_logits", "color_logits")}

    def __len__(self) -> int:
        return self.means.shape[0]

    def activated(self, posed: FramePoses | None = None) -> dict[str, np.ndarray]:
        """Values in the layout's Gaussian schema, world frame: posed at one frame, or the static part alone."""
        with torch.no_grad():
            if posed is None:
                keep = self.instance < 0
                means, quats = self.means[keep], self.quats[keep]
            else:
                means, quats, keep = posed.apply(self)
            return {
                "xyz": means.numpy().astype(np.float32),
                "scale": self.log_scales[keep].exp().numpy().astype(np.float32),
                "rotation": torch.nn.functional.normalize(quats, dim=1).numpy().astype(np.float32),
                "opacity": torch.sigmoid(self.opacity_logits[keep]).numpy().astype(np.float32),
                "color": torch.sigmoid(self.color_logits[keep]).numpy().astype(np.float32),
            }


@dataclass
class FramePoses:
    """Box -> world poses of the moving instances at one frame."""

    R_K33: torch.Tensor
    t_K3: torch.Tensor
    q_K4: torch.Tensor
    present_K: torch.Tensor

    @staticmethod
    def build(instances: list[str], poses: dict[str, np.ndarray]) -> FramePoses:
        k = max(len(instances), 1)
        R, t, q, present = np.tile(np.eye(3), (k, 1, 1)), np.zeros((k, 3)), np.tile([1.0, 0, 0, 0], (k, 1)), np.zeros(k)
        for i, inst in enumerate(instances):
            if inst in poses:
                R[i], t[i], present[i] = poses[inst][:3, :3], poses[inst][:3, 3], 1
                q[i] = matrix_to_quat_wxyz(poses[inst][:3, :3])
        f32 = torch.float32
        return FramePoses(
            torch.tensor(R, dtype=f32),
            torch.tensor(t, dtype=f32),
            torch.tensor(q, dtype=f32),
            torch.tensor(present, dtype=torch.bool),
        )

    def apply(self, g: Gaussians) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(world means, world quats, row mask) of the Gaussians visible at this frame; differentiable."""
        dyn = g.instance >= 0
        if not bool(dyn.any()):
            return g.means, g.quats, torch.ones(len(g), dtype=torch.bool)
        idx = g.instance.clamp(min=0)
        moved = torch.einsum("nij,nj->ni", self.R_K33[idx], g.means) + self.t_K3[idx]
        means = torch.where(dyn[:, None], moved, g.means)
        quats = torch.where(dyn[:, None], quat_mul(self.q_K4[idx], g.quats), g.quats)
        keep = ~dyn | self.present_K[idx]
        return means[keep], quats[keep], keep


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(p, 1e-4, 1 - 1e-4)
    return np.log(p / (1 - p))


def init_gaussians(
    points_N3: np.ndarray, colors_N3: np.ndarray, scales_N: np.ndarray, instance_N: np.ndarray | None = None
) -> Gaussians:
    n = len(points_N3)
    inst = np.full(n, -1) if instance_N is None else instance_N
    return Gaussians(
        instance=torch.tensor(inst, dtype=torch.long),
        means=torch.tensor(points_N3, dtype=torch.float32),
        log_scales=torch.tensor(np.log(scales_N)[:, None].repeat(3, 1), dtype=torch.float32),
        quats=torch.tensor(np.tile([1.0, 0, 0, 0], (n, 1)), dtype=torch.float32),
        opacity_logits=torch.full((n,), float(_logit(np.array(0.5))), dtype=torch.float32),
        color_logits=torch.tensor(_logit(colors_N3), dtype=torch.float32),
    )


def camera_of(v: View) -> Camera:
    h, w = v.rgb_HW3.shape[:2]
    return Camera.from_numpy(v.K_33, v.world2cam_44, w, h)


class Trainer:
    """Holds the Adam state so densification can grow and shrink it consistently."""

    def __init__(
        self,
        g: Gaussians,
        cfg: ReconstructConfig,
        extent: float,
        background: torch.Tensor,
        poses: dict[int, FramePoses],
    ):
        self.g, self.cfg, self.extent, self.poses = g, cfg, extent, poses
        self.background = background
        lrs = {
            "means": cfg.lr_means * extent,
            "log_scales": cfg.lr_scales,
            "quats": cfg.lr_quats,
            "opacity_logits": cfg.lr_opacities,
            "color_logits": cfg.lr_colors,
        }
        for p in g.params().values():
            p.requires_grad_(True)
        self.opt = torch.optim.Adam([{"params": [p], "lr": lrs[k], "name": k} for k, p in g.params().items()])
        if background.requires_grad:
            self.opt.add_param_group({"params": [background], "lr": 0.01, "name": "background"})
        self.grad_accum = torch.zeros(len(g))
        self.grad_count = torch.zeros(len(g))

    def render(self, v: View):
        g = self.g
        means, quats, keep = self.poses[v.frame].apply(g)
        return rasterize(
            means,
            g.log_scales[keep].exp(),
            quats,
            torch.sigmoid(g.opacity_logits[keep]),
            torch.sigmoid(g.color_logits[keep]),
            camera_of(v),
            background=torch.sigmoid(self.background),
            backend=self.cfg.backend,
        )

    def step(self, v: View) -> float:
        try:
            out = self.render(v)
        except ValueError as e:  # the rasterizer refuses NaN/inf parameters: the optimisation diverged
            raise NaNLossError(f"frame {v.frame} {v.camera}: {e}") from e
        gt = torch.from_numpy(v.rgb_HW3)
        loss = photometric(out.rgb, gt, self.cfg.ssim_weight)
        if self.cfg.depth_weight > 0:
            lidar = torch.from_numpy(v.lidar_depth_HW)
            mask = (lidar > 0) & (out.alpha > 0.5)
            if mask.any():
                loss = loss + self.cfg.depth_weight * (out.depth[mask] - lidar[mask]).abs().mean()
        if not torch.isfinite(loss):
            raise NaNLossError(f"frame {v.frame} {v.camera}: loss is {loss.item()}")
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        with torch.no_grad():
            gn = self.g.means.grad.norm(dim=1)
            seen = gn > 0
            self.grad_accum[seen] += gn[seen]
            self.grad_count[seen] += 1
        self.opt.step()
        return float(loss.item())

    # ------------------------------------------------------------------ densification
    def _replace(self, new: dict[str, torch.Tensor], keep: torch.Tensor, n_added: int, instance: torch.Tensor) -> None:
        """Swap in new parameter tensors; Adam moments of kept rows survive, added rows start at zero."""
        for group in self.opt.param_groups:
            name = group["name"]
            if name == "background":
                continue
            old = group["params"][0]
            t = new[name].detach().requires_grad_(True)
            state = self.opt.state.pop(old, None)
            if state:
                for k in ("exp_avg", "exp_avg_sq"):
                    pad = torch.zeros((n_added, *state[k].shape[1:]))
                    state[k] = torch.cat([state[k][keep], pad])
                self.opt.state[t] = state
            group["params"][0] = t
            setattr(self.g, name, t)
        self.g.instance = instance
        self.grad_accum = torch.zeros(len(self.g))
        self.grad_count = torch.zeros(len(self.g))

    def densify_and_prune(self) -> dict[str, int]:
        cfg, g = self.cfg, self.g
        with torch.no_grad():
            mean_grad = self.grad_accum / self.grad_count.clamp(min=1)
            big = g.log_scales.exp().max(dim=1).values > cfg.split_scale_m
            # A fixed share with the largest gradients, rather than an absolute threshold: our gradients are of
            # world-space centres, whose scale depends on the scene; 3DGS thresholds screen-space ones.
            n_hot = int(cfg.densify_fraction * len(g)) if len(g) < cfg.max_total_gaussians else 0
            hot = torch.zeros(len(g), dtype=torch.bool)
            if n_hot > 0:
                hot[torch.topk(mean_grad, n_hot).indices] = True
            hot &= self.grad_count > 0
            clone, split = hot & ~big, hot & big
            keep = (torch.sigmoid(g.opacity_logits) >= cfg.prune_opacity) & ~split
            params = g.params()
            new = {k: [p[keep]] for k, p in params.items()}
            inst = [g.instance[keep], g.instance[clone]]
            for k, p in params.items():
                new[k].append(p[clone])
            # Split: two children sampled inside the parent, each 1/1.6 its size (3DGS).
            idx = torch.nonzero(split).squeeze(1)
            if len(idx):
                std = g.log_scales[idx].exp()
                for _ in range(2):
                    offs = torch.randn_like(std) * std
                    rot = quat_to_rotmat(g.quats[idx])
                    new["means"].append(g.means[idx] + torch.einsum("nij,nj->ni", rot, offs))
                    new["log_scales"].append(g.log_scales[idx] - math.log(1.6))
                    for k in ("quats", "opacity_logits", "color_logits"):
                        new[k].append(params[k][idx])
                    inst.append(g.instance[idx])
            merged = {k: torch.cat(v) for k, v in new.items()}
            n_added = int(clone.sum()) + 2 * len(idx)
        self._replace(merged, keep, n_added, torch.cat(inst))
        return {"cloned": int(clone.sum()), "split": len(idx), "pruned": int((~keep).sum()) - len(idx)}

    def reset_opacity(self) -> None:
        with torch.no_grad():
            self.g.opacity_logits.clamp_(max=float(_logit(np.array(0.05))))
        for group in self.opt.param_groups:
            if group["name"] == "opacity_logits":
                self.opt.state.pop(group["params"][0], None)


def optimise(
    g: Gaussians,
    train: list[View],
    cfg: ReconstructConfig,
    log: Callable[[int, dict], None],
    extent: float,
    poses: dict[int, FramePoses],
) -> Trainer:
    """Run ``cfg.iterations`` steps over a seeded shuffle of the training views."""
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    if cfg.background is None:
        background = torch.tensor(_logit(np.array([0.7, 0.75, 0.8])), dtype=torch.float32, requires_grad=True)
    else:
        background = torch.tensor(_logit(np.asarray(cfg.background)), dtype=torch.float32)
    t = Trainer(g, cfg, extent, background, poses)
    order: list[int] = []
    base_lr = cfg.lr_means * extent
    for it in range(cfg.iterations):
        # Centres' lr decays exponentially to 1% (3DGS), so late steps refine instead of jitter.
        for group in t.opt.param_groups:
            if group["name"] == "means":
                group["lr"] = base_lr * 0.01 ** (it / max(cfg.iterations - 1, 1))
        if not order:
            order = list(rng.permutation(len(train)))
        loss = t.step(train[order.pop()])
        stats = {"loss": loss, "gaussians": float(len(g))}
        if cfg.densify_from <= it <= cfg.densify_until and it % cfg.densify_every == 0 and it > 0:
            stats.update({k: float(v) for k, v in t.densify_and_prune().items()})
        if cfg.opacity_reset_every and it > 0 and it % cfg.opacity_reset_every == 0 and it < cfg.densify_until:
            t.reset_opacity()
        log(it, stats)
    return t


def evaluate(t: Trainer, views: list[View]) -> list[dict]:
    """PSNR and SSIM per view (held-out views are never trained on)."""
    rows = []
    with torch.no_grad():
        for v in views:
            out = t.render(v)
            gt = torch.from_numpy(v.rgb_HW3)
            rows.append(
                {
                    "frame": v.frame,
                    "camera": v.camera,
                    "psnr": psnr(out.rgb, gt),
                    "ssim": float(ssim(out.rgb.clamp(0, 1), gt)),
                }
            )
    return rows
