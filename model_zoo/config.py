"""The component configs of ``model_zoo``: plain dataclasses, importable without torch.

Each is documented with (and used by) its component: ``selectors``, ``alignment``, ``adapter``, ``llm.qwen3_vl``,
``diffusion.rgbd_dual`` re-export theirs. They live here so that composing and validating a config (every ``gdwm``
command, before anything runs) never imports torch, transformers or diffusers.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Annotated

from annotated_types import Ge, Gt, Interval

SEED = Interval(ge=0, le=2**32 - 1)
"""A seed's range (numpy's legacy one, as ``gdwm.knobs.MAX_SEED``; model_zoo imports no platform code)."""

ATTRIBUTES: tuple[str, ...] = ("x", "s", "r", "o", "f")
"""Gaussian attributes of the attribute-aware projection: position, scale, rotation, opacity, feature."""


class PathSource(StrEnum):
    """Where the driving-aware selector's ego path P_traj comes from (``model.selector.path``).

    Leakage policy: the path is what the ego knows when it answers, never what it later did. ``route`` is the
    planned route it follows (navigation: the map's lane or road centreline, recorded by the dataset, not derived
    from the ego's motion), placed by the current ego pose only; ``extrapolated`` is the past ego positions carried
    on at the last step's velocity. Neither reads a recorded pose after the current frame, so the planning and
    trajectory answers cannot leak into the selection (``pipelines.understanding.data.FrameStore.selector_path``
    slices the poses to the current frame before building either).
    """

    route = "route"
    extrapolated = "extrapolated"


@dataclass
class SelectorConfig:
    """How a coarse selector picks ``K_c`` candidates; ``name`` picks the registered variant."""

    name: str = "driving_aware"
    """Registered selector variant: random, topk_uniform, topk_uniform_similarity, voxel_topk, driving_aware."""
    k_c: Annotated[int, Ge(0)] = 256
    """Number of candidates K_c; missing candidates are padded with invalid tokens."""
    voxel_size: Annotated[float, Gt(0)] = 2.0
    """Edge of the cubic voxel grid (metres, anchored at the ego origin) of VoxelTopK and uniform spatial sampling."""
    uniform_fraction: Annotated[float, Interval(ge=0, le=1)] = 0.5
    """topk_uniform(_similarity): share of K_c filled by uniform spatial sampling (the rest is ranked)."""
    similarity_fraction: Annotated[float, Interval(ge=0, le=1)] = 0.25
    """topk_uniform_similarity: share of K_c taken by top text-Gaussian similarity (out of the ranked share)."""
    w_q: Annotated[float, Ge(0)] = 1.0
    """Weight w_q of the intrinsic quality Q_i in S_i."""
    w_t: Annotated[float, Ge(0)] = 1.0
    """Weight w_t of the trajectory relevance T_i in S_i."""
    sigma_traj: Annotated[float, Gt(0)] = 5.0
    """Spatial influence range sigma_traj (metres) of the trajectory prior T_i."""
    seed: Annotated[int, SEED] = 0
    """Seed of the random variants when the caller passes no generator (gdwm's YAML sets it to the trial seed)."""
    coverage_first: bool = True
    """voxel_topk/driving_aware: on truncation keep VoxelTopK before TopK (False: top K_c of the union by score)."""
    path: PathSource = PathSource.route
    """driving_aware: the ego path of T_i: the planned ``route`` ahead of the ego (the paper's path ahead), or the
    past positions ``extrapolated`` at constant velocity. Never the recorded future poses (see ``PathSource``)."""
    route_ahead_m: Annotated[float, Gt(0)] = 30.0
    """driving_aware with ``path=route``: metres of the route ahead of the ego that become waypoints (1 m apart)."""

    def __post_init__(self) -> None:
        checks = [
            (self.k_c >= 0, f"k_c must be >= 0, got {self.k_c}"),
            (self.voxel_size > 0, f"voxel_size must be > 0 metres, got {self.voxel_size}"),
            (0 <= self.uniform_fraction <= 1, f"uniform_fraction must be in [0, 1], got {self.uniform_fraction}"),
            (
                0 <= self.similarity_fraction <= 1,
                f"similarity_fraction must be in [0, 1], got {self.similarity_fraction}",
            ),
            (self.w_q >= 0 and self.w_t >= 0 and self.w_q + self.w_t > 0, self._weights_msg()),
            (self.sigma_traj > 0, f"sigma_traj must be > 0 metres, got {self.sigma_traj}"),
            (self.route_ahead_m > 0, f"route_ahead_m must be > 0 metres, got {self.route_ahead_m}"),
        ]
        for ok, msg in checks:
            if not ok:
                raise ValueError(f"SelectorConfig '{self.name}': {msg}")
        try:
            self.path = PathSource(self.path)
        except ValueError:
            raise ValueError(
                f"SelectorConfig '{self.name}': path must be one of {[p.value for p in PathSource]}, got {self.path!r}"
            ) from None

    def _weights_msg(self) -> str:
        return f"w_q and w_t must be >= 0 with w_q + w_t > 0, got w_q={self.w_q}, w_t={self.w_t}"


@dataclass
class AlignmentConfig:
    name: str = "kl"
    """Alignment variant: none | kl."""
    weight: Annotated[float, Ge(0)] = 0.1
    """lambda_KL, the weight of L_KL in the understanding loss."""
    warmup_steps: Annotated[int, Ge(0)] = 100
    """Linear warm-up alpha(t) = min(1, t / warmup_steps); 0 means alpha = 1 from the first step."""
    eps: Annotated[float, Gt(0)] = 1e-4
    """epsilon added to both variances."""


@dataclass
class ProjectionConfig:
    fourier_features: Annotated[int, Ge(1)] = 16
    """Rows of the learnable Fourier map B (the position embedding has 2x this many dims)."""
    fourier_scale: Annotated[float, Gt(0)] = 0.05
    """Init std of B, in 1/metres (0.05 -> periods of ~20 m)."""
    mlp_ratio: Annotated[int, Ge(1)] = 2
    """Hidden width of the residual MLP aligner, times H."""
    attributes: tuple[str, ...] = ATTRIBUTES
    """Attributes that enter h~ (a subset of x, s, r, o, f; ablations drop "f")."""


@dataclass
class FineAdapterConfig:
    name: str = "query_xattn"
    """Fine adapter variant: similarity | query_xattn | identity."""
    k_f: Annotated[int, Ge(1)] = 16
    """World tokens K_f per sample."""
    heads: Annotated[int, Ge(1)] = 4
    """Attention heads of query_xattn (must divide H)."""


def identity_adapter_name(k_c: int, k_f: int) -> str:
    """``name`` of ``conf/model/fine_adapter/identity.yaml``, resolved when the config is composed: the identity adapter
    hands the K_c coarse candidates to the LLM as they are, so K_c must equal K_f (a larger K_c would keep only the
    first K_f, silently dropping whatever the selector ranked last, such as a uniform branch)."""
    if int(k_c) != int(k_f):
        raise ValueError(
            f"model/fine_adapter=identity passes the coarse candidates through as the world tokens, so "
            f"model.selector.k_c ({k_c}) must equal model.fine_adapter.k_f ({k_f}); set model.selector.k_c={k_f} "
            f"or choose another fine adapter"
        )
    return "identity"


RESOLVERS = {"gdwm_identity_adapter": identity_adapter_name}
"""OmegaConf resolvers of the model configs (registered by the ``pipelines`` plugin before anything composes)."""


def register_resolvers() -> None:
    from omegaconf import OmegaConf  # only where configs are composed

    for name, fn in RESOLVERS.items():
        if not OmegaConf.has_resolver(name):
            OmegaConf.register_new_resolver(name, fn)


@dataclass
class LLMConfig:
    name: str = "qwen3_vl"
    """Registered variant name."""
    path: str | None = None
    """Local checkpoint directory for full runs (config.json, safetensors, tokenizer files); never downloaded."""
    tiny: bool = True
    """Build a tiny random model of the same classes and a BPE tokenizer trained on the corpus (``path`` ignored)."""
    hidden_size: Annotated[int, Ge(1)] = 64
    """Tiny text model width H (= the vision tower's ``out_hidden_size``)."""
    num_layers: Annotated[int, Ge(1)] = 2
    """Tiny text model decoder layers."""
    num_heads: Annotated[int, Ge(1)] = 4
    """Tiny text model attention heads."""
    num_kv_heads: Annotated[int, Ge(1)] = 2
    """Tiny text model key/value heads (grouped-query attention)."""
    intermediate_size: Annotated[int, Ge(1)] = 128
    """Tiny text model MLP width."""
    vocab_size: Annotated[int, Ge(1)] = 600
    """Target BPE vocabulary of the tiny tokenizer, special tokens included (a small corpus may give fewer)."""
    max_length: Annotated[int, Ge(1)] = 384
    """Sequence limit of one sample (prompt + answer) in tokens."""
    image_max_pixels: Annotated[int, Ge(1)] = 16384
    """Image processor's upper bound on pixels per image (tiny: small images, few tokens)."""
    dtype: str = "float32"
    """Parameter dtype (``bfloat16`` on CUDA)."""
    seed: Annotated[int, SEED] = 0
    """Seed of the tiny flavor's random initialisation (gdwm's YAML sets it to the trial seed)."""
    pretrain_steps: Annotated[int, Ge(0)] = 0
    """Tiny flavor: full-parameter steps after the random init, standing in for a pretrained checkpoint (what it
    learns from is ``pretrain_on``)."""
    pretrain_on: str = "text"
    """``text``: next-token steps on the corpus, each string a document (the domain's words, not the tasks).
    ``instructions``: the training split's (instruction, answer) pairs in the chat template, text only (no images,
    no world tokens), loss on the answer: what an instruction-tuned VLM brings (answer formats, the prior of each
    question kind), never the scene, which the tokenizer and lora stages must learn to read."""
    pretrain_lr: Annotated[float, Gt(0)] = 3e-3
    """Adam learning rate of that warm-up."""
    pretrain_batch_size: Annotated[int, Ge(1)] = 32
    """Documents per warm-up step."""


@dataclass
class DiffusionConfig:
    name: str = "rgbd_dual"
    """Registered variant name."""
    path: str | None = None
    """Local directory with ``unet/`` and ``vae/`` subfolders (diffusers save_pretrained layout); never downloaded."""
    tiny: bool = True
    """Build tiny random UNet/VAE configs of the same classes (CPU, seconds); ``path`` is ignored."""
    image_size: Annotated[tuple[int, int], Ge(1)] = (48, 80)
    """(H, W) the model works at; inputs are resized by the caller."""
    latent_channels: Annotated[int, Ge(1)] = 4
    """L: channels of one VAE latent (the target d has 2L)."""
    unet_channels: Annotated[tuple[int, ...], Ge(1)] = (32, 64)
    """Tiny UNet ``block_out_channels`` (one down/up block each; all but the first use cross-attention)."""
    vae_channels: Annotated[tuple[int, ...], Ge(1)] = (16, 32)
    """Tiny VAE ``block_out_channels`` (downsample factor 2**(len-1))."""
    cross_attention_dim: Annotated[int, Ge(1)] = 64
    """Width of C_L (the LLM hidden size); a loaded UNet with another width gets a learned projection."""
    low_level: bool = True
    """Ablation switch: C_I, C_D enter the UNet input (False: zeros in their channels and in the mask). The reference
    latent d_ref is not a low-level condition and stays on: the paper's low-level conditions are C_I and C_D (the
    Gaussians projected into the target view) and F_theta takes d_ref as an input of its own beside them."""
    high_level: bool = True
    """Ablation switch: C_L enters through cross-attention (False: the learned null token always)."""
    cond_dropout: Annotated[float, Interval(ge=0, le=1)] = 0.1
    """Probability of replacing C_L by the null condition in training (classifier-free guidance)."""
    guidance_scale: Annotated[float, Ge(0)] = 2.0
    """CFG scale at sampling (1 = off)."""
    num_train_timesteps: Annotated[int, Ge(1)] = 1000
    """Diffusion steps of the training schedule."""
    sample_steps: Annotated[int, Ge(1)] = 20
    """DDIM steps at sampling."""
    max_depth: Annotated[float, Gt(0)] = 80.0
    """Depth in metres mapped to +1 in pseudo-RGB (farther is clamped)."""
    seed: Annotated[int, SEED] = 0
    """Seed of the tiny flavor's random initialisation (and of a fresh null token)."""
