"""Geometry-aware Gaussian adapter: attribute projection and fine adapters (Sec. Geometry-aware Gaussian Adapter).

``AttributeProjection`` maps each coarse candidate's attributes (position, scale, rotation, opacity, decoded
foundation feature) to an LLM-hidden token ``g_i`` (Eq. g_i). A fine adapter then turns the ``K_c`` candidate
tokens into ``K_f`` world tokens:

* ``fine_adapter/query_xattn`` (journal): ``K_f`` learned queries modulated by the pooled text embedding attend to
  the candidates (Eq. q~_j, Eq. z_j).
* ``fine_adapter/similarity`` (conference version): the ``K_f`` candidates most cosine-similar to the pooled text.
* ``fine_adapter/identity`` (conference rows Random / Top-K+Uniform): the ``K_c == K_f`` candidates unchanged; any
  other ``K_c`` is refused (a config error when composed, a ``ValueError`` here), since keeping the first ``K_f``
  would drop what the selector ranked last (the uniform branch of ``topk_uniform``).

Every fine adapter: ``forward(g_BKH, mask_BK, text_BLH, text_mask_BL) -> (z_BFH, z_mask_BF)``.

Legend: ``B`` batch, ``K`` candidates (``K_c``), ``F`` world tokens (``K_f``), ``H`` LLM hidden size, ``C`` decoded
feature dim ``d_f``, ``L`` text length, ``P`` attributes, ``R`` Fourier rows.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from model_zoo.config import (  # torch-free, so config composition never loads torch
    ATTRIBUTES,
    FineAdapterConfig,
    ProjectionConfig,
)
from model_zoo.registry import register


def fourier_embedding(xyz_BK3: torch.Tensor, b: nn.Linear) -> torch.Tensor:
    """Eq. phi_pos(x) = [sin(2 pi B x), cos(2 pi B x)], ``[B, K, 3] -> [B, K, 2R]``."""
    proj_BKR = 2 * math.pi * b(xyz_BK3)
    return torch.cat([proj_BKR.sin(), proj_BKR.cos()], dim=-1)


class AttributeProjection(nn.Module):
    """Attribute-aware Gaussian projection: ``h~ = sum_p lambda_p h^p`` and ``g = h~ + MLP(LN(h~))`` (Eq. g_i).

    Inputs are activated attributes (scale > 0 in metres, opacity in [0, 1]), as the data layout stores them.
    """

    def __init__(self, cfg: ProjectionConfig, hidden: int, feature_dim: int) -> None:
        super().__init__()
        unknown = [a for a in cfg.attributes if a not in ATTRIBUTES]
        if unknown or not cfg.attributes or len(set(cfg.attributes)) != len(cfg.attributes):
            raise ValueError(
                f"attribute projection: attributes must be distinct names from {list(ATTRIBUTES)}, "
                f"got {list(cfg.attributes)}"
            )
        if min(cfg.fourier_features, cfg.mlp_ratio, hidden, feature_dim) < 1:
            raise ValueError(
                f"attribute projection: fourier_features, mlp_ratio, hidden and feature_dim must be positive, "
                f"got {cfg.fourier_features}, {cfg.mlp_ratio}, {hidden}, {feature_dim}"
            )
        self.cfg = cfg
        self.attributes = tuple(cfg.attributes)
        self.fourier = nn.Linear(3, cfg.fourier_features, bias=False)
        nn.init.normal_(self.fourier.weight, std=cfg.fourier_scale)
        widths = {"x": 2 * cfg.fourier_features, "s": 3, "r": 4, "o": 1, "f": feature_dim}
        self.proj = nn.ModuleDict({a: nn.Linear(widths[a], hidden) for a in self.attributes})
        # lambda_p, one per entry of ``attributes``, in that order
        self.gates = nn.Parameter(torch.ones(len(self.attributes)))
        self.norm = nn.LayerNorm(hidden)
        self.mlp = nn.Sequential(
            nn.Linear(hidden, cfg.mlp_ratio * hidden), nn.GELU(), nn.Linear(cfg.mlp_ratio * hidden, hidden)
        )

    def forward(
        self,
        xyz_BK3: torch.Tensor,
        scale_BK3: torch.Tensor,
        rotation_BK4: torch.Tensor,
        opacity_BK: torch.Tensor,
        feature_BKC: torch.Tensor,
    ) -> torch.Tensor:
        """Aligned candidate tokens ``g_BKH`` (Eq. g_i); padded candidates are projected too, callers mask them."""
        inputs = {
            "x": fourier_embedding(xyz_BK3, self.fourier),
            # clamp: padded candidates may carry scale 0, whose log would poison LN with -inf
            "s": scale_BK3.clamp_min(1e-8).log(),
            "r": F.normalize(rotation_BK4, dim=-1),
            "o": opacity_BK.unsqueeze(-1),
            "f": feature_BKC,
        }
        h_BKH = sum(self.gates[p] * self.proj[a](inputs[a]) for p, a in enumerate(self.attributes))
        return h_BKH + self.mlp(self.norm(h_BKH))


def pooled_text(text_BLH: torch.Tensor, text_mask_BL: torch.Tensor) -> torch.Tensor:
    """Eq. e_q: mean of the text embeddings over valid positions, ``[B, H]``; zeros where none is valid."""
    count_B1 = text_mask_BL.sum(dim=1, keepdim=True).clamp_min(1).to(text_BLH.dtype)
    return text_BLH.masked_fill(~text_mask_BL.unsqueeze(-1), 0).sum(dim=1) / count_B1


def _pad_tokens(z_BFH: torch.Tensor, z_mask_BF: torch.Tensor, k_f: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Right-pad to ``k_f`` tokens with zeros / False."""
    missing = k_f - z_BFH.shape[1]
    if missing <= 0:
        return z_BFH, z_mask_BF
    return F.pad(z_BFH, (0, 0, 0, missing)), F.pad(z_mask_BF, (0, missing), value=False)


def _check_inputs(who: str, g_BKH: torch.Tensor, mask_BK: torch.Tensor, text_BLH: torch.Tensor) -> None:
    if g_BKH.ndim != 3 or mask_BK.shape != g_BKH.shape[:2] or mask_BK.dtype != torch.bool:
        raise ValueError(
            f"{who}: expected g [B, K, H] and a bool mask [B, K], got {list(g_BKH.shape)} and "
            f"{list(mask_BK.shape)} {mask_BK.dtype}"
        )
    if text_BLH.shape[0] != g_BKH.shape[0] or text_BLH.shape[-1] != g_BKH.shape[-1]:
        raise ValueError(f"{who}: text {list(text_BLH.shape)} does not match g {list(g_BKH.shape)} in B or H")


class SimilarityAdapter(nn.Module):
    """Conference version: the ``K_f`` valid candidates with the highest ``cos(g_i, e_q)``, in descending order."""

    def __init__(self, k_f: int) -> None:
        super().__init__()
        self.k_f = k_f

    def forward(
        self, g_BKH: torch.Tensor, mask_BK: torch.Tensor, text_BLH: torch.Tensor, text_mask_BL: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        _check_inputs("fine_adapter/similarity", g_BKH, mask_BK, text_BLH)
        e_BH = pooled_text(text_BLH, text_mask_BL)
        cos_BK = F.cosine_similarity(g_BKH, e_BH.unsqueeze(1), dim=-1)
        cos_BK = cos_BK.masked_fill(~mask_BK, -torch.inf)
        k = min(self.k_f, g_BKH.shape[1])
        idx_BF = cos_BK.topk(k, dim=1, sorted=True).indices
        z_mask_BF = mask_BK.gather(1, idx_BF)
        z_BFH = g_BKH.gather(1, idx_BF.unsqueeze(-1).expand(-1, -1, g_BKH.shape[-1]))
        z_BFH = z_BFH.masked_fill(~z_mask_BF.unsqueeze(-1), 0)
        return _pad_tokens(z_BFH, z_mask_BF, self.k_f)


class QueryCrossAttentionAdapter(nn.Module):
    """Journal version: text-conditioned Perceiver-style cross-attention (Eq. q~_j, Eq. z_j).

    ``q~_j = q_j + W_t e_q``; ``z_j = MHA(W_q q~_j, W_k g, W_v g)`` over the valid candidates. A sample with no
    valid candidate gets zero tokens and an all-False mask; otherwise every world token is valid.
    """

    def __init__(self, k_f: int, hidden: int, heads: int) -> None:
        super().__init__()
        if hidden % heads:
            raise ValueError(f"fine_adapter/query_xattn: heads={heads} must divide the hidden size {hidden}")
        self.queries_FH = nn.Parameter(torch.randn(k_f, hidden) * 0.02)  # q_j^L
        self.text_mod = nn.Linear(hidden, hidden)  # W_t
        self.attn = nn.MultiheadAttention(hidden, heads, batch_first=True)

    @property
    def k_f(self) -> int:
        return self.queries_FH.shape[0]

    def forward(
        self, g_BKH: torch.Tensor, mask_BK: torch.Tensor, text_BLH: torch.Tensor, text_mask_BL: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        _check_inputs("fine_adapter/query_xattn", g_BKH, mask_BK, text_BLH)
        e_BH = pooled_text(text_BLH, text_mask_BL)
        q_BFH = self.queries_FH.unsqueeze(0) + self.text_mod(e_BH).unsqueeze(1)
        # zero the padding so that its values (even NaN) cannot leak through a 0 attention weight
        g_BKH = g_BKH.masked_fill(~mask_BK.unsqueeze(-1), 0)
        has_any_B = mask_BK.any(dim=1)
        # an all-masked row makes softmax NaN; let empty samples attend to their zeros and discard the result
        key_padding_BK = ~mask_BK & has_any_B.unsqueeze(1)
        z_BFH, _ = self.attn(q_BFH, g_BKH, g_BKH, key_padding_mask=key_padding_BK, need_weights=False)
        z_BFH = torch.where(has_any_B[:, None, None], z_BFH, torch.zeros_like(z_BFH))
        return z_BFH, has_any_B.unsqueeze(1).expand(-1, self.k_f).clone()


class IdentityAdapter(nn.Module):
    """The candidates unchanged as the world tokens; there must be exactly ``K_f`` of them (``K_c == K_f``)."""

    def __init__(self, k_f: int) -> None:
        super().__init__()
        self.k_f = k_f

    def forward(
        self, g_BKH: torch.Tensor, mask_BK: torch.Tensor, text_BLH: torch.Tensor, text_mask_BL: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        _check_inputs("fine_adapter/identity", g_BKH, mask_BK, text_BLH)
        if g_BKH.shape[1] != self.k_f:
            raise ValueError(
                f"fine_adapter/identity: got K_c={g_BKH.shape[1]} candidates for K_f={self.k_f} world tokens; "
                f"model.selector.k_c must equal model.fine_adapter.k_f"
            )
        return g_BKH, mask_BK


def _checked(cfg: FineAdapterConfig | None, name: str) -> FineAdapterConfig:
    cfg = FineAdapterConfig(name=name) if cfg is None else cfg
    if cfg.k_f < 1:
        raise ValueError(f"fine_adapter/{name}: k_f must be positive, got {cfg.k_f}")
    return cfg


@register("fine_adapter", "similarity")
def build_similarity(cfg: FineAdapterConfig | None = None, hidden: int = 64) -> SimilarityAdapter:
    """Cosine top-K_f selection (no parameters); ``hidden`` is unused and kept for a uniform builder signature."""
    return SimilarityAdapter(_checked(cfg, "similarity").k_f)


@register("fine_adapter", "query_xattn")
def build_query_xattn(cfg: FineAdapterConfig | None = None, hidden: int = 64) -> QueryCrossAttentionAdapter:
    """Text-conditioned cross-attention; the defaults (K_f=16, H=64, 4 heads) are its tiny flavor."""
    cfg = _checked(cfg, "query_xattn")
    return QueryCrossAttentionAdapter(cfg.k_f, hidden, cfg.heads)


@register("fine_adapter", "identity")
def build_identity(cfg: FineAdapterConfig | None = None, hidden: int = 64) -> IdentityAdapter:
    """Pass-through of the K_c == K_f candidates; ``hidden`` is unused."""
    return IdentityAdapter(_checked(cfg, "identity").k_f)
