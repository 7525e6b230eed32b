"""``diffusion/rgbd_dual``: dual-condition RGB-D latent diffusion (Sec. Instruction-controllable 4D Scene Generation).

A diffusers ``UNet2DConditionModel`` F_theta denoises the target latent d = concat(z_I, z_D) of one view, where
z_I = E_vae(I) and z_D = E_vae(D^rgb) come from one frozen ``AutoencoderKL`` (Eq. z_I, z_D). Its input stacks, along
channels, the noisy target d_t (2L), the reference view's latent d_ref (2L), the low-level conditions C_I and C_D
encoded by the same VAE (2L) and the condition validity mask at latent resolution (1): 6L + 1 channels. The
high-level condition C_L (LLM hidden states) enters through cross-attention; a learned null token stands in for it
in classifier-free-guidance dropout, at unconditional sampling and when the ``high_level`` ablation is off
(Tab. world). The ``low_level`` ablation zeros C_I, C_D and the mask only: d_ref is the reference view, an input of
F_theta of its own (Eq. v_hat lists it apart from the low-level conditions), present in every row of Tab. world. It
carries appearance but not the target view's geometry, the "spatial anchor" the high-level-only row lacks. The UNet
predicts v (Eq. v_t) for both latents; training minimises Eq. L_gen, sampling runs DDIM.

Full runs load a LOCAL directory with ``unet/`` and ``vae/`` (diffusers ``save_pretrained`` layout); ``tiny``
builds random tiny configs of the same classes whose VAE is trained by ``fit_vae`` as its own upstream step.
diffusers is imported when a model is built, so looking variants up stays cheap.

Legend: B batch, H x W image pixels (``cfg.image_size``), h x w latent pixels, L latent channels (the VAE's; in
``c_L_BLH`` L is the C_L sequence length and H the LLM hidden size = ``cross_attention_dim``).
"""

from __future__ import annotations

import json
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from model_zoo.config import DiffusionConfig  # torch-free, so config composition never loads torch
from model_zoo.diffusion.vpred import add_noise, alphas_sigmas, depth_to_rgb, rgb_to_depth, v_target
from model_zoo.registry import register

EXPECTED_LAYOUT = (
    "unet/ and vae/ subfolders in diffusers save_pretrained layout (config.json + diffusion_pytorch_model.safetensors)"
)
# Stable Diffusion 2's v-prediction noise schedule: pretrained UNets loaded from `path` were trained on it.
_SCHEDULE = {"beta_schedule": "scaled_linear", "beta_start": 0.00085, "beta_end": 0.012, "clip_sample": False}


def _tiny_unet(cfg: DiffusionConfig, latent_hw: tuple[int, int]) -> Any:
    from diffusers import UNet2DConditionModel

    n = len(cfg.unet_channels)
    L = cfg.latent_channels
    return UNet2DConditionModel(
        sample_size=latent_hw,
        in_channels=6 * L + 1,
        out_channels=2 * L,
        down_block_types=("DownBlock2D",) + ("CrossAttnDownBlock2D",) * (n - 1),
        up_block_types=("CrossAttnUpBlock2D",) * (n - 1) + ("UpBlock2D",),
        block_out_channels=tuple(cfg.unet_channels),
        layers_per_block=1,
        cross_attention_dim=cfg.cross_attention_dim,
        attention_head_dim=4,  # diffusers' legacy name: this is the number of heads
        norm_num_groups=min(8, *cfg.unet_channels),
    )


def _tiny_vae(cfg: DiffusionConfig) -> Any:
    from diffusers import AutoencoderKL

    n = len(cfg.vae_channels)
    return AutoencoderKL(
        in_channels=3,
        out_channels=3,
        down_block_types=("DownEncoderBlock2D",) * n,
        up_block_types=("UpDecoderBlock2D",) * n,
        block_out_channels=tuple(cfg.vae_channels),
        layers_per_block=1,
        latent_channels=cfg.latent_channels,
        norm_num_groups=min(8, *cfg.vae_channels),
        sample_size=max(cfg.image_size),
    )


def _check_dir(path: str | None) -> Path:
    if path is None:
        raise FileNotFoundError(
            f"diffusion/rgbd_dual: cfg.path is not set; full runs (tiny=False) need {EXPECTED_LAYOUT}"
        )
    root = Path(path)
    if not root.is_dir():
        raise FileNotFoundError(
            f"diffusion/rgbd_dual: weight directory {root} does not exist; expected {EXPECTED_LAYOUT}"
        )
    missing = [f"{sub}/" for sub in ("unet", "vae") if not (root / sub / "config.json").is_file()]
    if missing:
        raise FileNotFoundError(
            f"diffusion/rgbd_dual: weight directory {root} lacks {' and '.join(missing)}; expected {EXPECTED_LAYOUT}"
        )
    return root


def _fit_unet(unet: Any, cfg: DiffusionConfig, seed: int) -> Any:
    """Make a loaded UNet take 6L+1 input channels, give 2L outputs and read C_L of width ``cross_attention_dim``.

    A pretrained SD UNet has ``in_channels`` = L: its ``conv_in`` is widened with zero-initialised extra input
    channels, so at step 0 it sees only the noisy RGB latent, as pretrained. ``out_channels`` = L is doubled by
    copying the head, so the depth latent starts from the same v-predictor. A cross-attention width other than
    C_L's gets a learned ``encoder_hid_proj`` (diffusers' ``text_proj``), stored in the UNet's config and weights.
    """
    L = cfg.latent_channels
    c_in, c_out = 6 * L + 1, 2 * L
    gen = torch.Generator().manual_seed(seed)
    if unet.config.in_channels != c_in:
        old = unet.conv_in
        if old.in_channels > c_in:
            raise ValueError(f"diffusion/rgbd_dual: loaded UNet has in_channels {old.in_channels} > 6L+1 = {c_in}")
        new = nn.Conv2d(c_in, old.out_channels, old.kernel_size, old.stride, old.padding).to(old.weight)
        with torch.no_grad():
            new.weight.zero_()
            new.weight[:, : old.in_channels] = old.weight
            new.bias.copy_(old.bias)
        unet.conv_in = new
        unet.register_to_config(in_channels=c_in)
    if unet.config.out_channels != c_out:
        old = unet.conv_out
        if old.out_channels != L:
            raise ValueError(
                f"diffusion/rgbd_dual: loaded UNet has out_channels {old.out_channels}; expected {L} or {c_out}"
            )
        new = nn.Conv2d(old.in_channels, c_out, old.kernel_size, old.stride, old.padding).to(old.weight)
        with torch.no_grad():
            new.weight.copy_(old.weight.repeat(2, 1, 1, 1))
            new.bias.copy_(old.bias.repeat(2))
        unet.conv_out = new
        unet.register_to_config(out_channels=c_out)
    xattn = unet.config.cross_attention_dim
    if not isinstance(xattn, int):
        raise ValueError(f"diffusion/rgbd_dual: per-block cross_attention_dim {xattn} is not supported")
    width = unet.config.encoder_hid_dim if unet.encoder_hid_proj is not None else xattn
    if width != cfg.cross_attention_dim:
        if unet.encoder_hid_proj is not None:
            raise ValueError(
                f"diffusion/rgbd_dual: loaded UNet projects C_L of width {width}, cfg.cross_attention_dim is "
                f"{cfg.cross_attention_dim}"
            )
        proj = nn.Linear(cfg.cross_attention_dim, xattn).to(unet.conv_in.weight)
        with torch.no_grad():
            proj.weight.normal_(0.0, cfg.cross_attention_dim**-0.5, generator=gen)
            proj.bias.zero_()
        unet.encoder_hid_proj = proj
        unet.register_to_config(encoder_hid_dim=cfg.cross_attention_dim, encoder_hid_dim_type="text_proj")
    return unet


def _null_token(cfg: DiffusionConfig) -> torch.Tensor:
    gen = torch.Generator().manual_seed(cfg.seed)
    return torch.randn(1, 1, cfg.cross_attention_dim, generator=gen) * 0.02


class RGBDDual(nn.Module):
    """F_theta(d_t, d_ref, C_I, C_D, C_L, s_t): ``.unet`` (trained), ``.vae`` (frozen), ``.null_token``, schedulers.

    ``scheduler`` is the training ``DDPMScheduler``; ``sample_scheduler`` the ``DDIMScheduler`` used by ``sample``;
    both predict v.
    """

    def __init__(self, cfg: DiffusionConfig, unet: Any, vae: Any, null_token: torch.Tensor | None = None) -> None:
        super().__init__()
        from diffusers import DDIMScheduler, DDPMScheduler

        L = cfg.latent_channels
        if vae.config.latent_channels != L:
            raise ValueError(f"diffusion/rgbd_dual: VAE has {vae.config.latent_channels} latent channels, cfg says {L}")
        if (unet.config.in_channels, unet.config.out_channels) != (6 * L + 1, 2 * L):
            raise ValueError(
                f"diffusion/rgbd_dual: UNet maps {unet.config.in_channels} -> {unet.config.out_channels} channels; "
                f"expected 6L+1 = {6 * L + 1} -> 2L = {2 * L}"
            )
        vae_factor = 2 ** (len(vae.config.block_out_channels) - 1)
        unet_factor = 2 ** (len(unet.config.block_out_channels) - 1)
        H, W = cfg.image_size
        if H % (vae_factor * unet_factor) or W % (vae_factor * unet_factor):
            raise ValueError(
                f"diffusion/rgbd_dual: image_size {tuple(cfg.image_size)} must be divisible by "
                f"{vae_factor * unet_factor} (VAE x{vae_factor}, UNet x{unet_factor})"
            )
        self.cfg = cfg
        self.latent_hw = (H // vae_factor, W // vae_factor)
        self.unet = unet
        self.vae = vae
        self.vae.requires_grad_(False)
        self.vae.eval()
        token = _null_token(cfg) if null_token is None else null_token.detach().clone()
        if tuple(token.shape) != (1, 1, cfg.cross_attention_dim):
            raise ValueError(f"diffusion/rgbd_dual: null token has shape {list(token.shape)}")
        self.null_token = nn.Parameter(token.to(torch.float32))
        sched = dict(_SCHEDULE, num_train_timesteps=cfg.num_train_timesteps, prediction_type="v_prediction")
        self.scheduler = DDPMScheduler(**sched)
        self.sample_scheduler = DDIMScheduler(**sched, set_alpha_to_one=False, steps_offset=1)

    # ------------------------------------------------------------------ construction, persistence

    @classmethod
    def tiny(cls, cfg: DiffusionConfig) -> RGBDDual:
        """Random tiny UNet and VAE of the diffusers classes, seeded with ``cfg.seed``; ``fit_vae`` trains the VAE."""
        vae_factor = 2 ** (len(cfg.vae_channels) - 1)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(cfg.seed)
            unet = _tiny_unet(cfg, (cfg.image_size[0] // vae_factor, cfg.image_size[1] // vae_factor))
            vae = _tiny_vae(cfg)
        return cls(cfg, unet, vae)

    @classmethod
    def load(cls, cfg: DiffusionConfig) -> RGBDDual:
        """UNet and VAE from the local directory ``cfg.path`` (``unet/``, ``vae/``; ``null_token.pt`` if present).

        A UNet whose ``in_channels`` is not 6L+1 (a pretrained SD UNet has L) is adapted: its ``conv_in`` gets
        zero-initialised extra input channels (and see ``_fit_unet`` for the output head and C_L width).
        """
        from diffusers import AutoencoderKL, UNet2DConditionModel

        root = _check_dir(cfg.path)
        unet = UNet2DConditionModel.from_pretrained(str(root / "unet"), local_files_only=True)
        vae = AutoencoderKL.from_pretrained(str(root / "vae"), local_files_only=True)
        token_file = root / "null_token.pt"
        token = torch.load(token_file, map_location="cpu", weights_only=True) if token_file.is_file() else None
        return cls(cfg, _fit_unet(unet, cfg, cfg.seed), vae, token)

    @classmethod
    def from_pretrained(cls, path: str | Path) -> RGBDDual:
        """A model written by ``save``: its ``rgbd.json`` config, ``unet/``, ``vae/`` and ``null_token.pt``."""
        root = Path(path)
        missing = [f for f in ("rgbd.json", "null_token.pt") if not (root / f).is_file()]
        if missing:
            raise FileNotFoundError(
                f"diffusion/rgbd_dual: {root} lacks {' and '.join(missing)}; expected what RGBDDual.save writes "
                f"(rgbd.json, null_token.pt, unet/, vae/)"
            )
        raw = json.loads((root / "rgbd.json").read_text())
        for key in ("image_size", "unet_channels", "vae_channels"):
            raw[key] = tuple(raw[key])
        return cls.load(replace(DiffusionConfig(**raw), path=str(root), tiny=False))

    def save(self, path: str | Path) -> None:
        """Write ``unet/``, ``vae/`` (save_pretrained), ``rgbd.json`` (the config) and ``null_token.pt``."""
        root = Path(path)
        root.mkdir(parents=True, exist_ok=True)
        self.unet.save_pretrained(str(root / "unet"))
        self.vae.save_pretrained(str(root / "vae"))
        (root / "rgbd.json").write_text(json.dumps(asdict(self.cfg), indent=2) + "\n")
        torch.save(self.null_token.detach().cpu(), root / "null_token.pt")

    def train(self, mode: bool = True) -> RGBDDual:
        """Train mode for the UNet only: the VAE stays frozen in eval mode (``fit_vae`` trains it on its own)."""
        super().train(mode)
        self.vae.eval()
        return self

    def trainable_parameters(self) -> list[nn.Parameter]:
        """The UNet's parameters and the null token (the VAE is frozen)."""
        return [p for p in self.parameters() if p.requires_grad]

    @property
    def device(self) -> torch.device:
        return self.null_token.device

    # ------------------------------------------------------------------ latents and conditions

    def encode(self, x_B3HW: torch.Tensor) -> torch.Tensor:
        """z = E_vae(x): the VAE posterior mean (deterministic) x ``scaling_factor``; ``x`` in [-1, 1]."""
        z = self.vae.encode(x_B3HW.to(self.device, torch.float32)).latent_dist.mean
        shift = self.vae.config.shift_factor
        return (z - (shift or 0.0)) * self.vae.config.scaling_factor

    def decode(self, z_BLhw: torch.Tensor) -> torch.Tensor:
        """x = D_vae(z) in VAE space (about [-1, 1]); inverse of ``encode``'s scaling."""
        shift = self.vae.config.shift_factor
        return self.vae.decode(z_BLhw / self.vae.config.scaling_factor + (shift or 0.0)).sample

    def _check(self, name: str, x: torch.Tensor, channels: int | None) -> None:
        H, W = self.cfg.image_size
        want = (H, W) if channels is None else (channels, H, W)
        if x.ndim != len(want) + 1 or tuple(x.shape[1:]) != want:
            shape = "[B, H, W]" if channels is None else f"[B, {channels}, H, W]"
            raise ValueError(
                f"diffusion/rgbd_dual: {name} must be {shape} with (H, W) = {(H, W)}, got {list(x.shape)} "
                f"(the caller resizes to cfg.image_size)"
            )

    @torch.no_grad()
    def rgbd_latent(self, rgb_B3HW: torch.Tensor, depth_BHW: torch.Tensor) -> torch.Tensor:
        """d = concat(z_I, z_D) ``[B, 2L, h, w]`` from RGB in [0, 1] and depth in metres (Eq. z_I, z_D)."""
        z_rgb = self.encode(rgb_B3HW * 2.0 - 1.0)
        z_depth = self.encode(depth_to_rgb(depth_BHW.to(self.device, torch.float32), self.cfg.max_depth))
        return torch.cat([z_rgb, z_depth], dim=1)

    @torch.no_grad()
    def low_level(self, cond_rgb: torch.Tensor, cond_depth: torch.Tensor, cond_mask: torch.Tensor) -> torch.Tensor:
        """[E_vae(C_I), E_vae(C_D^rgb), mask at latent resolution] ``[B, 2L + 1, h, w]``; zeros if ``low_level`` is off.

        Pixels outside ``cond_mask`` carry no evidence and are zeroed before encoding; the mask is area-averaged,
        i.e. the fraction of valid pixels under each latent pixel.
        """
        B = cond_rgb.shape[0]
        if not self.cfg.low_level:
            return torch.zeros(B, 2 * self.cfg.latent_channels + 1, *self.latent_hw, device=self.device)
        m_B1HW = cond_mask.to(self.device, torch.float32).unsqueeze(1)
        c = self.rgbd_latent(
            cond_rgb.to(self.device, torch.float32) * m_B1HW, cond_depth.to(self.device) * m_B1HW[:, 0]
        )
        return torch.cat([c, F.interpolate(m_B1HW, size=self.latent_hw, mode="area")], dim=1)

    def _null(self, B: int, S: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The null condition padded to S tokens: the null token first, masked-out zeros after it."""
        tokens = torch.cat(
            [self.null_token.expand(B, 1, -1), self.null_token.new_zeros(B, S - 1, self.null_token.shape[-1])], 1
        )
        mask = torch.zeros(B, S, device=self.device)
        mask[:, 0] = 1.0
        return tokens, mask

    def high_level(
        self, c_L_BLH: torch.Tensor | None, c_L_mask_BL: torch.Tensor | None, B: int, drop_B: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Cross-attention tokens and mask: C_L, or the null condition where ``drop_B`` (always if high_level off)."""
        if c_L_BLH is None or not self.cfg.high_level:
            return self._null(B, 1)
        E = self.cfg.cross_attention_dim
        if c_L_BLH.ndim != 3 or c_L_BLH.shape[0] != B or c_L_BLH.shape[2] != E or c_L_BLH.shape[1] == 0:
            raise ValueError(f"diffusion/rgbd_dual: C_L must be [B={B}, L > 0, H={E}], got {list(c_L_BLH.shape)}")
        S = c_L_BLH.shape[1]
        tokens = c_L_BLH.to(self.device, torch.float32)
        mask = (
            torch.ones(B, S, device=self.device) if c_L_mask_BL is None else c_L_mask_BL.to(self.device, torch.float32)
        )
        if drop_B is not None and bool(drop_B.any()):
            null_tokens, null_mask = self._null(B, S)
            drop_B = drop_B.to(self.device)
            tokens = torch.where(drop_B[:, None, None], null_tokens, tokens)
            mask = torch.where(drop_B[:, None], null_mask, mask)
        return tokens, mask

    # ------------------------------------------------------------------ training and sampling

    def loss(
        self,
        target_rgb: torch.Tensor,
        target_depth: torch.Tensor,
        ref_rgb: torch.Tensor,
        ref_depth: torch.Tensor,
        cond_rgb: torch.Tensor,
        cond_depth: torch.Tensor,
        cond_mask: torch.Tensor,
        c_L_BLH: torch.Tensor | None,
        c_L_mask_BL: torch.Tensor | None,
        generator: torch.Generator | None = None,
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """L_gen = || F_theta(d_t, d_ref, C_I, C_D, C_L, s_t) - v_t ||^2, mean over elements (Eq. L_gen).

        Images ``[B, 3, H, W]`` in [0, 1], depths and ``cond_mask`` ``[B, H, W]`` (metres; 1 = valid). t is uniform
        over the training steps; in train mode C_L is replaced by the null condition with probability
        ``cond_dropout`` (the draw is made in eval mode too, so a generator gives the same t and eps either way).
        Returns the loss and ``{"loss", "loss_rgb", "loss_depth"}`` (the last two over the z_I and z_D halves).
        """
        for name, x, ch in (
            ("target_rgb", target_rgb, 3),
            ("target_depth", target_depth, None),
            ("ref_rgb", ref_rgb, 3),
            ("ref_depth", ref_depth, None),
            ("cond_rgb", cond_rgb, 3),
            ("cond_depth", cond_depth, None),
            ("cond_mask", cond_mask, None),
        ):
            self._check(name, x, ch)
        B, L = target_rgb.shape[0], self.cfg.latent_channels
        d = self.rgbd_latent(target_rgb, target_depth)
        context = torch.cat([self.rgbd_latent(ref_rgb, ref_depth), self.low_level(cond_rgb, cond_depth, cond_mask)], 1)
        gen_device = generator.device if generator is not None else torch.device("cpu")
        t_B = torch.randint(0, self.cfg.num_train_timesteps, (B,), generator=generator, device=gen_device)
        eps = torch.randn(d.shape, generator=generator, device=gen_device).to(self.device)
        drop_B = torch.rand(B, generator=generator, device=gen_device) < self.cfg.cond_dropout
        t_B = t_B.to(self.device)
        alpha, sigma = alphas_sigmas(self.scheduler, t_B)
        tokens, mask = self.high_level(c_L_BLH, c_L_mask_BL, B, drop_B if self.training else None)
        x = torch.cat([add_noise(d, eps, alpha, sigma), context], dim=1)
        v_hat = self.unet(x, t_B, encoder_hidden_states=tokens, encoder_attention_mask=mask).sample
        v = v_target(d, eps, alpha, sigma)
        loss_rgb = F.mse_loss(v_hat[:, :L], v[:, :L])
        loss_depth = F.mse_loss(v_hat[:, L:], v[:, L:])
        loss = (loss_rgb + loss_depth) / 2.0  # equal halves: the mean over all elements
        return loss, {"loss": loss.item(), "loss_rgb": loss_rgb.item(), "loss_depth": loss_depth.item()}

    @torch.no_grad()
    def sample(
        self,
        ref_rgb: torch.Tensor,
        ref_depth: torch.Tensor,
        cond_rgb: torch.Tensor,
        cond_depth: torch.Tensor,
        cond_mask: torch.Tensor,
        c_L: torch.Tensor | None,
        c_L_mask: torch.Tensor | None,
        generator: torch.Generator | None = None,
        steps: int | None = None,
        guidance_scale: float | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """DDIM (v-prediction) from noise to (RGB ``[B, 3, H, W]`` in [0, 1], depth ``[B, H, W]`` in metres).

        Classifier-free guidance v = v_null + s (v_C_L - v_null) runs when s != 1 and ``high_level`` is on.
        """
        for name, x, ch in (
            ("ref_rgb", ref_rgb, 3),
            ("ref_depth", ref_depth, None),
            ("cond_rgb", cond_rgb, 3),
            ("cond_depth", cond_depth, None),
            ("cond_mask", cond_mask, None),
        ):
            self._check(name, x, ch)
        from diffusers import DDIMScheduler

        steps = self.cfg.sample_steps if steps is None else steps
        scale = self.cfg.guidance_scale if guidance_scale is None else guidance_scale
        B, L = ref_rgb.shape[0], self.cfg.latent_channels
        sched = DDIMScheduler.from_config(self.sample_scheduler.config)  # set_timesteps mutates it
        sched.set_timesteps(steps, device=self.device)
        context = torch.cat([self.rgbd_latent(ref_rgb, ref_depth), self.low_level(cond_rgb, cond_depth, cond_mask)], 1)
        tokens, mask = self.high_level(c_L, c_L_mask, B)
        guided = scale != 1.0 and self.cfg.high_level
        if guided:
            null_tokens, null_mask = self._null(B, tokens.shape[1])
            tokens, mask, context = (
                torch.cat([null_tokens, tokens]),
                torch.cat([null_mask, mask]),
                context.repeat(2, 1, 1, 1),
            )
        gen_device = generator.device if generator is not None else torch.device("cpu")
        shape = (B, 2 * L, *self.latent_hw)
        x = torch.randn(shape, generator=generator, device=gen_device).to(self.device) * sched.init_noise_sigma
        for t in sched.timesteps:
            x_in = sched.scale_model_input(torch.cat([x, x]) if guided else x, t)
            v = self.unet(torch.cat([x_in, context], 1), t, encoder_hidden_states=tokens, encoder_attention_mask=mask)
            v = v.sample
            if guided:
                v_null, v_cond = v.chunk(2)
                v = v_null + scale * (v_cond - v_null)
            x = sched.step(v, t, x).prev_sample
        rgb = ((self.decode(x[:, :L]) + 1.0) / 2.0).clamp(0.0, 1.0)
        depth = rgb_to_depth(self.decode(x[:, L:]), self.cfg.max_depth)
        return rgb, depth

    def fit_vae(
        self,
        images_B3HW: torch.Tensor,
        steps: int = 200,
        lr: float = 1e-3,
        seed: int = 0,
        batch_size: int | None = 32,
        kl_weight: float = 1e-4,
    ) -> list[float]:
        """Train the VAE on ``[N, 3, H, W]`` images in [0, 1]: RGB and pseudo-RGB depth (``(depth_to_rgb + 1) / 2``).

        The tiny flavor's upstream step, standing in for a pretrained VAE; images are mapped to [-1, 1] like every
        VAE input. Loss = L1 reconstruction of a posterior sample + ``kl_weight`` x per-element KL to N(0, I), Adam.
        Each step draws ``batch_size`` images (None: all) with a generator seeded by ``seed``. Afterwards
        ``scaling_factor`` is set to 1 / std of the posterior means of all images (how SD chose 0.18215) so the UNet
        sees unit-variance latents, and the VAE is frozen again. Returns each step's L1 reconstruction loss (in
        [-1, 1] units), before that step's update.
        """
        if images_B3HW.ndim != 4 or images_B3HW.shape[1] != 3 or images_B3HW.shape[0] == 0:
            raise ValueError(
                f"diffusion/rgbd_dual: fit_vae expects images [N > 0, 3, H, W], got {list(images_B3HW.shape)}"
            )
        x_all = images_B3HW.detach().to(self.device, torch.float32) * 2.0 - 1.0
        gen = torch.Generator().manual_seed(seed)
        self.vae.requires_grad_(True)
        self.vae.train()
        opt = torch.optim.Adam(self.vae.parameters(), lr=lr)
        n = x_all.shape[0]
        losses: list[float] = []
        try:
            for _ in range(steps):
                x = (
                    x_all
                    if batch_size is None or batch_size >= n
                    else x_all[torch.randint(n, (batch_size,), generator=gen)]
                )
                post = self.vae.encode(x).latent_dist
                z = post.mean + post.std * torch.randn(post.mean.shape, generator=gen).to(self.device)
                rec = F.l1_loss(self.vae.decode(z).sample, x)
                kl = 0.5 * (post.mean.pow(2) + post.var - 1.0 - post.logvar).mean()
                opt.zero_grad(set_to_none=True)
                (rec + kl_weight * kl).backward()
                opt.step()
                losses.append(rec.item())
        finally:
            self.vae.requires_grad_(False)
            self.vae.eval()
        with torch.no_grad():
            means = [self.vae.encode(x).latent_dist.mean for x in x_all.split(batch_size or n)]
            std = torch.cat(means).std().item()
        self.vae.register_to_config(scaling_factor=1.0 / max(std, 1e-6))
        return losses


@register("diffusion", "rgbd_dual")
def build_rgbd_dual(cfg: DiffusionConfig | None = None) -> RGBDDual:
    """Tiny random UNet/VAE when ``cfg.tiny`` (the default), else ``RGBDDual.load`` from the local ``cfg.path``."""
    cfg = DiffusionConfig() if cfg is None else cfg
    return RGBDDual.tiny(cfg) if cfg.tiny else RGBDDual.load(cfg)
