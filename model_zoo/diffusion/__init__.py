"""Generation branch: ``rgbd_dual``, the dual-condition RGB-D latent diffusion (diffusers UNet + frozen VAE, v-pred)."""

from model_zoo.diffusion.rgbd_dual import DiffusionConfig, RGBDDual, build_rgbd_dual
from model_zoo.diffusion.vpred import add_noise, alphas_sigmas, depth_to_rgb, rgb_to_depth, v_target

__all__ = [
    "DiffusionConfig",
    "RGBDDual",
    "add_noise",
    "alphas_sigmas",
    "build_rgbd_dual",
    "depth_to_rgb",
    "rgb_to_depth",
    "v_target",
]
