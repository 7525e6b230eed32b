"""Compact feature autoencoder: z_i = E_z(f_i), f~_i = D_F(z_i) (Sec. Foundation-feature Gaussian Tokenizer).

Each Gaussian stores only the code ``z_i`` (``d_z`` numbers); ``D_F`` decodes it to a ``d_f``-dim foundation
feature before rendering. Both halves are small MLPs applied per feature (no batch statistics), so a Gaussian's
decoded feature never depends on which other Gaussians share its batch.

Variants: ``feature_tokenizer/foundation`` (``d_z`` configurable, default 16) and ``feature_tokenizer/langsplat3``
(``d_z = 3``, the width of the public GaussianDWM release's ``_language_feature`` codes). A variant is a class:
``registry.get("feature_tokenizer", name).configure(d_f, d_z, hidden)`` is the config it trains with.

Legend: ``N`` features, ``C`` = ``d_f``, ``Z`` = ``d_z``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import ClassVar

import torch
from torch import nn

from model_zoo.distill_math import l_ae
from model_zoo.registry import register


@dataclass
class FeatureAEConfig:
    d_f: int = 64
    """Foundation feature dimension (the encoder's ``d_f``)."""
    d_z: int = 16
    """Code dimension stored per Gaussian."""
    hidden: int = 128
    """Width of the hidden layers of E_z and D_F."""
    layers: int = 2
    """Linear layers in each of E_z and D_F (1 = a single linear map)."""


def _mlp(d_in: int, hidden: int, d_out: int, layers: int) -> nn.Sequential:
    dims = [d_in] + [hidden] * (layers - 1) + [d_out]
    mods: list[nn.Module] = []
    for i in range(layers):
        mods.append(nn.Linear(dims[i], dims[i + 1]))
        if i < layers - 1:
            mods.append(nn.GELU())
    return nn.Sequential(*mods)


class FeatureAutoencoder(nn.Module):
    """E_z: ``[N, d_f] -> [N, d_z]`` and D_F: ``[N, d_z] -> [N, d_f]``, each an MLP of ``cfg.layers`` layers."""

    def __init__(self, cfg: FeatureAEConfig) -> None:
        super().__init__()
        if min(cfg.d_f, cfg.d_z, cfg.hidden, cfg.layers) < 1:
            raise ValueError(f"feature autoencoder: d_f, d_z, hidden and layers must be positive, got {cfg}")
        self.cfg = cfg
        self.encoder = _mlp(cfg.d_f, cfg.hidden, cfg.d_z, cfg.layers)
        self.decoder = _mlp(cfg.d_z, cfg.hidden, cfg.d_f, cfg.layers)

    @property
    def d_f(self) -> int:
        return self.cfg.d_f

    @property
    def d_z(self) -> int:
        return self.cfg.d_z

    def encode(self, f_NC: torch.Tensor) -> torch.Tensor:
        """E_z (Eq. z_i = E_z(f_i))."""
        return self.encoder(f_NC)

    def decode(self, z_NZ: torch.Tensor) -> torch.Tensor:
        """D_F (Eq. f^_i = D_F(z_i)); the decoded features are what the rasterizer renders."""
        return self.decoder(z_NZ)

    def forward(self, f_NC: torch.Tensor) -> torch.Tensor:
        """Reconstruction ``D_F(E_z(f))``."""
        return self.decode(self.encode(f_NC))


def fit_autoencoder(
    features_NC: torch.Tensor,
    cfg: FeatureAEConfig,
    steps: int = 500,
    lr: float = 1e-3,
    seed: int = 0,
    batch_size: int | None = None,
) -> tuple[FeatureAutoencoder, list[float]]:
    """Train a fresh autoencoder on ``features_NC`` with L_ae (squared L2, Eq. L_ae); Adam, deterministic on CPU.

    ``batch_size`` None uses every feature each step; otherwise minibatches drawn from a generator seeded with
    ``seed``. Returns the model (eval mode) and the L_ae of every step's batch, before that step's update.
    """
    if features_NC.ndim != 2 or features_NC.shape[1] != cfg.d_f or features_NC.shape[0] == 0:
        raise ValueError(f"fit_autoencoder: expected features [N > 0, d_f={cfg.d_f}], got {list(features_NC.shape)}")
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = FeatureAutoencoder(cfg)
    f_NC = features_NC.detach().to(torch.float32)
    gen = torch.Generator().manual_seed(seed)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    n = f_NC.shape[0]
    losses: list[float] = []
    model.train()
    for _ in range(steps):
        batch = f_NC if batch_size is None or batch_size >= n else f_NC[torch.randint(n, (batch_size,), generator=gen)]
        loss = l_ae(model(batch), batch)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        losses.append(loss.item())
    return model.eval(), losses


@register("feature_tokenizer", "foundation")
class FoundationTokenizer(FeatureAutoencoder):
    """Compact foundation-feature autoencoder, ``d_z`` a setting; ``FeatureAEConfig()`` (64 -> 16) is its tiny
    flavor."""

    fixed_d_z: ClassVar[int | None] = None
    """The code width the variant fixes, or None where ``d_z`` is the caller's."""

    def __init__(self, cfg: FeatureAEConfig | None = None) -> None:
        super().__init__(self.configure() if cfg is None else replace(cfg))

    @classmethod
    def configure(
        cls, d_f: int = FeatureAEConfig.d_f, d_z: int = FeatureAEConfig.d_z, hidden: int = FeatureAEConfig.hidden
    ) -> FeatureAEConfig:
        """The variant's config for ``d_f``-dim features: ``d_z`` as asked, unless the variant fixes its own."""
        return FeatureAEConfig(d_f=d_f, d_z=d_z if cls.fixed_d_z is None else cls.fixed_d_z, hidden=hidden)


@register("feature_tokenizer", "langsplat3")
class LangSplat3Tokenizer(FoundationTokenizer):
    """3-dim codes, the width of the public release's ``_language_feature``; ``d_z`` is fixed to 3."""

    fixed_d_z = 3

    def __init__(self, cfg: FeatureAEConfig | None = None) -> None:
        if cfg is not None and cfg.d_z != self.fixed_d_z:
            raise ValueError(
                f"feature_tokenizer/langsplat3: d_z is fixed to 3 (the release's _language_feature), got {cfg.d_z}"
            )
        super().__init__(cfg)
