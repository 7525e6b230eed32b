"""The world model: coarse selector -> decoded features -> attribute projection -> fine adapter -> Z_G -> Qwen3-VL.

Loss (Sec. Scene Understanding with Gaussian World Tokens): L = L_LM + lambda_KL alpha(t) L_KL, with L_LM the
prefix-LM loss on response tokens of X_in = Concat(V, Z_G, T).

Saved as a directory (what the tokenizer and lora stages publish and inference loads)::

    world.json     component configs, feature width, per-scene decoder configs, LoRA settings
    adapter.pt     state dict of the per-scene D_F, the shared feature head, the projection and the fine adapter
                   (weights_only=True)
    llm/           tiny flavor: the LLM and its tokenizer (full runs reference llm.path instead)
    lora/          peft adapter of the lora stage

Legend: ``B`` batch, ``K`` candidates K_c, ``F`` world tokens K_f, ``H`` LLM hidden, ``C`` d_f, ``N`` Gaussians.
"""

from __future__ import annotations

import contextlib
import json
import logging
import re
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from model_zoo import registry
from model_zoo.adapter import AttributeProjection, FineAdapterConfig, ProjectionConfig, pooled_text
from model_zoo.alignment import AlignmentConfig
from model_zoo.feature_ae import FeatureAEConfig, FeatureAutoencoder
from model_zoo.llm.qwen3_vl import LLMConfig, WorldLLM
from model_zoo.llm.text import collate, encode_sample
from model_zoo.selectors import Selection, SelectorConfig, SelectorInputs
from pipelines.understanding.config import LoraStageConfig, WorldConfig
from pipelines.understanding.data import FrameStore, QASample

log = logging.getLogger(__name__)

WORLD_FILE, ADAPTER_FILE, LLM_DIR, LORA_DIR = "world.json", "adapter.pt", "llm", "lora"


@dataclass
class Components:
    """Every config the world model is built from (the ``model.*`` subtrees)."""

    world: WorldConfig
    selector: SelectorConfig
    projection: ProjectionConfig
    fine_adapter: FineAdapterConfig
    alignment: AlignmentConfig
    llm: LLMConfig

    @classmethod
    def from_model_cfg(cls, model: dict) -> Components:
        proj = dict(model["projection"])
        proj["attributes"] = tuple(proj.get("attributes", ProjectionConfig.attributes))
        return cls(
            WorldConfig(**model["world"]),
            SelectorConfig(**model["selector"]),
            ProjectionConfig(**proj),
            FineAdapterConfig(**model["fine_adapter"]),
            AlignmentConfig(**model["alignment"]),
            LLMConfig(**model["llm"]),
        )

    def to_dict(self) -> dict:
        return {
            k: asdict(getattr(self, k)) for k in ("world", "selector", "projection", "fine_adapter", "alignment", "llm")
        }


PICKED = ("xyz", "scale", "rotation", "opacity", "code")


def _gather(t_N: torch.Tensor, index_K: torch.Tensor, mask_K: torch.Tensor, fill: float) -> torch.Tensor:
    """``t_N[index_K]`` with the padding slots set to ``fill`` (an empty frame has nothing to index)."""
    picked = t_N[index_K] if len(t_N) else torch.zeros((len(index_K), *t_N.shape[1:]), dtype=t_N.dtype)
    keep = mask_K.view(-1, *([1] * (picked.dim() - 1)))
    return torch.where(keep, picked, torch.full_like(picked, fill))


class FeatureHead(nn.Module):
    """What training fine-tunes of the feature decoding, shared by every scene: ``f + MLP(f)`` on the per-scene
    D_F's output, the MLP's last layer zero-initialised so an untrained head is the identity.

    Each scene's D_F is fitted by the distill stage on that scene alone (a code space of its own), so it stays
    frozen here: fine-tuning it would train only the training scenes' decoders and leave held-out scenes with
    untrained ones. The head is one module for all scenes, so a held-out scene's features pass through exactly the
    parameters the training scenes trained.
    """

    def __init__(self, d_f: int, hidden: int):
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(d_f, hidden), nn.GELU(), nn.Linear(hidden, d_f))
        nn.init.zeros_(self.mlp[-1].weight)
        nn.init.zeros_(self.mlp[-1].bias)

    def forward(self, f_NC: torch.Tensor) -> torch.Tensor:
        return f_NC + self.mlp(f_NC)


def _scene_key(scene: str) -> str:
    """ModuleDict keys may not contain dots."""
    return re.sub(r"[^0-9A-Za-z_]", "_", scene)


class WorldModel(nn.Module):
    """Gaussian world tokens for Qwen3-VL (Sec. Geometry-aware Gaussian Adapter)."""

    def __init__(self, comp: Components, llm: WorldLLM, decoders: dict[str, tuple[FeatureAEConfig, nn.Module]]):
        super().__init__()
        self.comp = comp
        self.llm = llm
        self.lm = llm.model  # registered, so .to(device) and DDP see the LLM's parameters
        self.decoder_cfgs = {s: c for s, (c, _) in decoders.items()}
        self.decoders = nn.ModuleDict({_scene_key(s): d for s, (_, d) in decoders.items()})
        widths = {c.d_f for c in self.decoder_cfgs.values()}
        if len(widths) > 1:
            raise ValueError(f"scenes' feature decoders disagree on d_f: {sorted(widths)} (one encoder per run)")
        self.feature_dim = widths.pop() if widths else 1
        hidden = max((c.hidden for c in self.decoder_cfgs.values()), default=FeatureAEConfig.hidden)
        self.feature_head = FeatureHead(self.feature_dim, hidden)
        self.projection = AttributeProjection(comp.projection, llm.hidden_size, self.feature_dim)
        self.fine = registry.build("fine_adapter", comp.fine_adapter.name, comp.fine_adapter, llm.hidden_size)
        self.align = registry.build("alignment", comp.alignment.name, comp.alignment)
        self.selector = registry.build("selector", comp.selector.name, comp.selector)
        self.decoders.requires_grad_(False)  # per-scene: see FeatureHead
        self.feature_head.requires_grad_(comp.world.train_decoder)
        if not comp.world.gaussian_tokens:  # image-only: the adapter exists (one saved layout) but never trains
            self.feature_head.requires_grad_(False)
            self.projection.requires_grad_(False)
            self.fine.requires_grad_(False)
        self.peft: Any = None

    @property
    def gaussian_tokens(self) -> bool:
        return self.comp.world.gaussian_tokens

    @property
    def k_f(self) -> int:
        return self.comp.fine_adapter.k_f

    # ---- inputs -----------------------------------------------------------------------------------------------
    def encode(
        self,
        samples: Sequence[QASample],
        store: FrameStore,
        *,
        with_answer: bool,
        gaussian: bool | None = None,
        padding_side: str = "right",
    ) -> dict:
        """Token ids, labels, images and per-sample masks of the instruction tokens for one batch."""
        gaussian = self.gaussian_tokens if gaussian is None else gaussian
        pixel_values, grid, n_tokens = self.llm.image_inputs([store.images(s) for s in samples])
        encoded = [
            encode_sample(
                self.llm,
                sample_id=s.sample_id,
                instruction=s.instruction,
                answer=s.answer if with_answer else None,
                image_tokens=n_tokens[i],
                k_f=self.k_f,
                gaussian=gaussian,
                max_length=self.comp.llm.max_length,
            )
            for i, s in enumerate(samples)
        ]
        batch = collate(encoded, self.llm.pad_token_id, padding_side=padding_side)
        return {
            "batch": batch,
            "pixel_values": pixel_values,
            "image_grid_thw": grid,
            "image_counts": [len(n) for n in n_tokens],
            "text_mask": batch["instruction_mask"].bool(),
            "gaussian": gaussian,
        }

    def feature_decoder(self, scene: str) -> nn.Sequential:
        """The decoding chain of ``scene``'s codes: its frozen D_F, then the feature head every scene shares."""
        key = _scene_key(scene)
        if key not in self.decoders:
            raise KeyError(
                f"{scene}: no feature decoder D_F for this scene (the model has {sorted(self.decoder_cfgs)})"
            )
        return nn.Sequential(self.decoders[key], self.feature_head)

    def _decoded(self, scene: str, code_KZ: torch.Tensor) -> torch.Tensor:
        return self.feature_decoder(scene)(code_KZ)

    def candidates(self, samples: Sequence[QASample], store: FrameStore, e_BH: torch.Tensor) -> dict[str, torch.Tensor]:
        """Coarse selection per sample, gathered into [B, K_c, ...] tensors with the padding mask."""
        device = e_BH.device
        rows = []
        for b, s in enumerate(samples):
            g = store.gaussians(s.scene, s.frame)
            if self.selector.needs_similarity:
                sel = self._select(store, s, g, self._text_similarity(s.scene, g, e_BH[b]))
            else:  # the frame alone decides (its Gaussians and path, a seeded generator): once per frame and store
                key = ("selection", s.scene, s.frame, repr(self.comp.selector))
                sel = store.derived(key, lambda s=s, g=g: self._select(store, s, g))
            # Padding slots are neutral (unit scale, zeros elsewhere), never a copy of whatever Gaussian 0 is.
            row = {k: _gather(g[k], sel.index, sel.mask, 1.0 if k == "scale" else 0.0) for k in PICKED}
            row["feature"] = self._decoded(s.scene, row.pop("code").to(device)) * sel.mask[:, None].to(device)
            row["mask"] = sel.mask
            rows.append(row)
        return {k: torch.stack([r[k] for r in rows]).to(device) for k in rows[0]}

    def _select(
        self, store: FrameStore, s: QASample, g: dict[str, torch.Tensor], similarity: torch.Tensor | None = None
    ) -> Selection:
        path = store.selector_path(s.scene, s.frame, self.comp.selector) if self.selector.needs_trajectory else None
        inputs = SelectorInputs(g["xyz"], g["scale"], g["rotation"], g["opacity"], path, similarity)
        return self.selector(inputs, generator=torch.Generator().manual_seed(self.comp.selector.seed))

    @torch.no_grad()
    def _text_similarity(self, scene: str, g: dict[str, torch.Tensor], e_H: torch.Tensor) -> torch.Tensor:
        """Text-Gaussian similarity of the conference selector: cosine between every Gaussian's projected token and
        the pooled instruction embedding."""
        if len(g["xyz"]) == 0:
            return torch.zeros(0)
        dev = e_H.device
        feats = self._decoded(scene, g["code"].to(dev))
        tok_NH = self.projection(
            g["xyz"][None].to(dev),
            g["scale"][None].to(dev),
            g["rotation"][None].to(dev),
            g["opacity"][None].to(dev),
            feats[None],
        )[0]
        return torch.nn.functional.cosine_similarity(tok_NH.float(), e_H.float()[None], dim=-1).cpu()

    def world_tokens(
        self, samples: Sequence[QASample], store: FrameStore, enc: dict
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Z_G [B, K_f, H] and its mask."""
        device = next(self.projection.parameters()).device
        text_BLH = self.llm.text_embeddings(enc["batch"]["input_ids"].to(device))
        text_mask = enc["text_mask"].to(device)
        e_BH = pooled_text(text_BLH, text_mask)
        c = self.candidates(samples, store, e_BH)
        g_BKH = self.projection(c["xyz"], c["scale"], c["rotation"], c["opacity"], c["feature"])
        return self.fine(g_BKH, c["mask"], text_BLH, text_mask)

    def image_tokens(self, enc: dict, features: Any = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Foundation image tokens Y_I per sample, padded to [B, M, H] with a mask (KL targets); from ``features``
        (the vision tower's output on the batch's images, ``WorldLLM.image_features``) when given."""
        per_image = (
            self.llm.image_tokens(enc["pixel_values"], enc["image_grid_thw"], features)
            if enc["pixel_values"] is not None
            else []
        )
        rows, i = [], 0
        for n in enc["image_counts"]:
            rows.append(torch.cat(per_image[i : i + n]) if n else torch.zeros(0, self.llm.hidden_size))
            i += n
        m = max((len(r) for r in rows), default=0)
        out = torch.zeros(len(rows), m, self.llm.hidden_size, device=rows[0].device if rows else "cpu")
        mask = torch.zeros(len(rows), m, dtype=torch.bool, device=out.device)
        for b, r in enumerate(rows):
            out[b, : len(r)] = r
            mask[b, : len(r)] = True
        return out, mask

    # ---- objective --------------------------------------------------------------------------------------------
    def forward(
        self, samples: Sequence[QASample], store: FrameStore, step: int
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """L_LM + lambda_KL alpha(t) L_KL on one batch, and its parts for logging (a forward, so DDP can wrap it)."""
        enc = self.encode(samples, store, with_answer=True)
        z, z_mask = self.world_tokens(samples, store, enc) if enc["gaussian"] else (None, None)
        align = z is not None and self.comp.alignment.name != "none"
        # L_KL's targets are the tokens the LLM consumes: one pass of the vision tower serves both (the tower is
        # frozen and draws no random numbers, so the loss and its gradients are those of two passes)
        features = None
        if align and enc["pixel_values"] is not None:
            features = self.llm.image_features(enc["pixel_values"], enc["image_grid_thw"])
        l_lm = self.llm.loss(enc["batch"], z, enc["pixel_values"], enc["image_grid_thw"], image_features=features)
        parts = {"loss_lm": float(l_lm.detach())}
        total = l_lm
        if align:
            img, img_mask = self.image_tokens(enc, features)
            weighted, raw = self.align(z, z_mask, img.detach(), img_mask, step)
            total = total + weighted
            parts["loss_kl"] = float(raw.detach())
        parts["loss"] = float(total.detach())
        return total, parts

    @torch.no_grad()
    def answer(self, samples: Sequence[QASample], store: FrameStore, max_new_tokens: int) -> list[str]:
        """Batched greedy decoding of the answers."""
        enc = self.encode(samples, store, with_answer=False, padding_side="left")
        z = self.world_tokens(samples, store, enc)[0] if enc["gaussian"] else None
        return self.llm.generate(enc["batch"], z, enc["pixel_values"], enc["image_grid_thw"], max_new_tokens)

    @torch.no_grad()
    def condition(self, samples: Sequence[QASample], store: FrameStore) -> tuple[torch.Tensor, torch.Tensor]:
        """C_L = Phi_LLM(Z_G, q): the LLM's last hidden states over each prompt ``[B, L, H]`` and their mask (the
        high-level condition of the generation branch)."""
        enc = self.encode(samples, store, with_answer=False)
        z = self.world_tokens(samples, store, enc)[0] if enc["gaussian"] else None
        hidden = self.llm.hidden_states(enc["batch"], z, enc["pixel_values"], enc["image_grid_thw"])
        return hidden.float(), enc["batch"]["attention_mask"].bool().to(hidden.device)

    # ---- LoRA, parameters, persistence -------------------------------------------------------------------------
    def add_lora(self, cfg: LoraStageConfig) -> None:
        """peft LoRA on the language model's ``target_modules`` (injected in place; the vision tower gets none)."""
        from peft import LoraConfig, get_peft_model

        names = "|".join(re.escape(m) for m in cfg.target_modules)
        lora = LoraConfig(
            r=cfg.rank, lora_alpha=cfg.alpha, lora_dropout=cfg.dropout, target_modules=rf".*language_model.*\.({names})"
        )
        self.peft = get_peft_model(self.llm.model, lora)

    def adapter_modules(self) -> dict[str, nn.Module]:
        return {
            "decoders": self.decoders,
            "feature_head": self.feature_head,
            "projection": self.projection,
            "fine": self.fine,
        }

    def freeze_llm(self) -> None:
        """Stage 1: the LLM is frozen (LoRA weights, once added, stay trainable)."""
        for name, p in self.lm.named_parameters():
            p.requires_grad_("lora_" in name)

    def trainable_parameters(self) -> list[nn.Parameter]:
        return [p for p in self.parameters() if p.requires_grad]

    def adapter_state(self) -> dict[str, torch.Tensor]:
        return {
            f"{k}.{n}": t.detach().cpu() for k, m in self.adapter_modules().items() for n, t in m.state_dict().items()
        }

    def load_adapter_state(self, state: dict[str, torch.Tensor]) -> None:
        for k, m in self.adapter_modules().items():
            prefix = f"{k}."
            sub = {n[len(prefix) :]: t for n, t in state.items() if n.startswith(prefix)}
            if k == "feature_head" and not sub:
                continue  # saved before the shared head existed: the identity head reproduces that model
            m.load_state_dict(sub)

    def lora_state(self) -> dict[str, torch.Tensor]:
        return {n: p.detach().cpu() for n, p in self.lm.named_parameters() if "lora_" in n}

    def load_lora_state(self, state: dict[str, torch.Tensor]) -> None:
        params = dict(self.lm.named_parameters())
        missing = sorted(set(state) - set(params))
        if missing:
            raise KeyError(f"LoRA state has parameters the model lacks: {missing[:3]}")
        with torch.no_grad():
            for n, t in state.items():
                params[n].copy_(t)

    def save(self, out: Path, *, save_llm: bool) -> None:
        out.mkdir(parents=True, exist_ok=True)
        meta = {
            "components": self.comp.to_dict(),
            "decoders": {s: asdict(c) for s, c in self.decoder_cfgs.items()},
            "lora": self.peft is not None,
        }
        (out / WORLD_FILE).write_text(json.dumps(meta, indent=2, sort_keys=True))
        torch.save(self.adapter_state(), out / ADAPTER_FILE)
        if save_llm and self.peft is None:
            self.llm.save(out / LLM_DIR)
        elif save_llm:  # the base weights without the injected LoRA layers (those go to lora/)
            clean = {k.replace(".base_layer", ""): v for k, v in self.lm.state_dict().items() if "lora_" not in k}
            self.lm.save_pretrained(str(out / LLM_DIR), state_dict=clean)
            self.llm.tokenizer.save_pretrained(str(out / LLM_DIR))
            self.llm.image_processor.save_pretrained(str(out / LLM_DIR))
        if self.peft is not None:
            # the base model is llm/ beside it (or llm.path), never the absolute path it was loaded from: the same
            # model saved from another workdir is the same bytes
            base = self.peft.get_base_model()
            named = [(base.config, "_name_or_path"), (base, "name_or_path")]  # the model card's two sources
            named += [(c, "base_model_name_or_path") for c in self.peft.peft_config.values()]
            before = [getattr(o, a) for o, a in named]
            for o, a in named:
                setattr(o, a, LLM_DIR)
            try:
                # LoRA never targets the embeddings here; "auto" would look llm/ up on the Hub to find out
                self.peft.save_pretrained(str(out / LORA_DIR), save_embedding_layers=False)
            finally:
                for (o, a), value in zip(named, before, strict=True):
                    setattr(o, a, value)


def load_decoders(scene_dirs: dict[str, Path]) -> dict[str, tuple[FeatureAEConfig, nn.Module]]:
    """D_F of every scene from the distill stage's ``decoder.pt`` / ``autoencoder.json``."""
    out = {}
    for scene, d in sorted(scene_dirs.items()):
        meta_path = d / "autoencoder.json"
        if not meta_path.is_file():
            raise FileNotFoundError(f"{scene}: distill output {d} has no autoencoder.json")
        cfg = FeatureAEConfig(**json.loads(meta_path.read_text())["config"])
        ae = FeatureAutoencoder(cfg)
        ae.load_state_dict(torch.load(d / "decoder.pt", map_location="cpu", weights_only=True))
        out[scene] = (cfg, ae.decoder)
    return out


def build_world_model(comp: Components, llm: WorldLLM, scene_dirs: dict[str, Path], seed: int) -> WorldModel:
    """A fresh world model: the adapter's initial weights come from ``seed`` alone, not from whatever the process's
    generator holds."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return WorldModel(comp, llm, load_decoders(scene_dirs) if comp.world.gaussian_tokens else {})


def load_world_model(path: Path, *, llm_path: str | None = None) -> WorldModel:
    """A saved world model (``save``'s layout); ``llm_path`` overrides where full runs' LLM weights are."""
    meta_path = path / WORLD_FILE
    if not meta_path.is_file():
        raise FileNotFoundError(f"{path}: not a saved world model ({WORLD_FILE} missing)")
    meta = json.loads(meta_path.read_text())
    comp = Components.from_model_cfg(meta["components"])
    llm_dir = path / LLM_DIR if (path / LLM_DIR).is_dir() else Path(llm_path or comp.llm.path or "")
    llm = WorldLLM.from_pretrained(llm_dir, comp.llm)  # the config's dtype and pixel bound, not the saved ones
    decoders = {}
    for scene, c in meta["decoders"].items():
        cfg = FeatureAEConfig(**c)
        decoders[scene] = (cfg, FeatureAutoencoder(cfg).decoder)
    model = WorldModel(comp, llm, decoders)
    model.load_adapter_state(torch.load(path / ADAPTER_FILE, map_location="cpu", weights_only=True))
    if meta["lora"]:
        from peft import PeftModel

        model.peft = PeftModel.from_pretrained(llm.model, str(path / LORA_DIR))
    return model


@contextlib.contextmanager
def autocast(device: torch.device) -> Iterator[None]:
    """bf16 autocast on CUDA, nothing on CPU."""
    if device.type == "cuda":
        with torch.autocast("cuda", dtype=torch.bfloat16):
            yield
    else:
        yield
