"""``encoder/qwen3_vl_vision``: the vision tower of a Qwen3-VL checkpoint as E_F (full runs; ``tiny`` on CPU).

The paper instantiates E_F with Qwen visual encoders (Sec. Foundation-feature Gaussian Tokenizer). This wraps
transformers' ``Qwen3VLVisionModel``:

- weights come from a LOCAL directory only (``QwenVisionConfig.path``): a full Qwen3-VL checkpoint (the tower's
  tensors under ``model.visual.``; the language model's tensors are never read) or a saved vision tower alone;
- preprocessing is transformers' ``Qwen2VLImageProcessorPil`` (the processor Qwen3-VL ships with, PIL backend):
  resize so both sides are multiples of ``patch_size * merge_size`` within the min/max pixel bounds, rescale to
  0..1, normalise with the checkpoint's ``image_mean``/``image_std``. Those come from ``preprocessor_config.json``
  when the directory has one, else from the Qwen3-VL release defaults (mean = std = 0.5, 65536..16777216 pixels)
  with patch/merge/temporal sizes from the vision config;
- the output tokens are put back on their grid, ``[h, w, d_f]``, and upsampled bilinearly to the image (each token
  at the centre of the image region its patch covers). ``feature="merged"`` takes the patch merger's output (the
  tokens the LLM consumes, ``d_f = out_hidden_size``, one per ``patch * merge`` px); ``feature="hidden"`` the last
  block's patch tokens (``d_f = hidden_size``, one per ``patch`` px).

transformers is imported when an encoder is built, so looking variants up stays cheap.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from model_zoo.encoders.base import EncoderSettings, FoundationEncoder, upsample_grid
from model_zoo.registry import register

EXPECTED_FILES = "config.json and model.safetensors (or model.safetensors.index.json with the shards it lists)"
# Qwen3-VL's released preprocessor_config.json values, used when a checkpoint directory has none.
QWEN3_VL_IMAGE_MEAN = (0.5, 0.5, 0.5)
QWEN3_VL_IMAGE_STD = (0.5, 0.5, 0.5)
QWEN3_VL_MIN_PIXELS = 65536
QWEN3_VL_MAX_PIXELS = 16777216
_MODEL_TYPES = ("qwen3_vl", "qwen3_vl_moe", "qwen3_vl_vision")
_TOWER_PREFIXES = ("model.visual.", "visual.", "")


@dataclass
class QwenVisionConfig:
    path: str | None = None
    """Local directory of a Qwen3-VL checkpoint (or of a saved vision tower); never downloaded."""
    tiny: bool = False
    """Build a tiny random tower of the same classes instead (CPU tests); ``path`` is then ignored."""
    feature: str = "merged"
    """Which tokens: ``merged`` (patch merger output, what the LLM sees) or ``hidden`` (last block, finer grid)."""
    dtype: str = "float32"
    """Compute dtype of the tower (``bfloat16`` on GPUs); the encoded map is always float32."""
    device: str = "cpu"
    """Device the tower runs on and the encoded map is returned on."""
    min_pixels: int | None = None
    """Override of the processor's lower pixel bound (``size.shortest_edge``); None keeps the checkpoint's."""
    max_pixels: int | None = None
    """Override of the processor's upper pixel bound (``size.longest_edge``); None keeps the checkpoint's."""
    seed: int = 0
    """Seed of the tiny flavor's random initialisation."""


def tiny_vision_config() -> Any:
    """A tiny ``Qwen3VLVisionConfig``: 2 blocks, width 32, 2 heads, 8 px patches, merged tokens of width 32."""
    from transformers.models.qwen3_vl import Qwen3VLVisionConfig

    return Qwen3VLVisionConfig(
        depth=2,
        hidden_size=32,
        intermediate_size=64,
        num_heads=2,
        patch_size=8,
        spatial_merge_size=2,
        temporal_patch_size=2,
        out_hidden_size=32,
        num_position_embeddings=64,
        deepstack_visual_indexes=[],
    )


def _check_files(path: Path) -> None:
    if not path.is_dir():
        raise FileNotFoundError(
            f"qwen3_vl_vision: checkpoint directory {path} does not exist; expected {EXPECTED_FILES}"
        )
    missing = [] if (path / "config.json").is_file() else ["config.json"]
    if not (path / "model.safetensors").is_file() and not (path / "model.safetensors.index.json").is_file():
        missing.append("model.safetensors (or model.safetensors.index.json)")
    if missing:
        raise FileNotFoundError(
            f"qwen3_vl_vision: checkpoint directory {path} lacks {' and '.join(missing)}; expected {EXPECTED_FILES}"
        )


def _vision_config(path: Path) -> Any:
    from transformers.models.qwen3_vl import Qwen3VLVisionConfig

    raw = json.loads((path / "config.json").read_text())
    model_type = raw.get("model_type")
    if model_type not in _MODEL_TYPES:
        raise ValueError(
            f"qwen3_vl_vision: {path / 'config.json'} has model_type {model_type!r}, not one of {_MODEL_TYPES}"
        )
    return Qwen3VLVisionConfig.from_dict(raw.get("vision_config", raw))


def _tensor_files(path: Path) -> dict[str, Path]:
    """Tensor name -> the safetensors file holding it."""
    from safetensors import safe_open

    if (path / "model.safetensors").is_file():
        with safe_open(str(path / "model.safetensors"), framework="pt") as f:
            return dict.fromkeys(f.keys(), path / "model.safetensors")
    index = json.loads((path / "model.safetensors.index.json").read_text())
    return {name: path / shard for name, shard in index["weight_map"].items()}


def load_vision_tower(path: str | Path) -> Any:
    """``Qwen3VLVisionModel`` with its weights read from the local checkpoint directory ``path`` (float32, CPU).

    Only the tower's tensors are read (lazily, per safetensors file). ``from_pretrained`` on the vision class is not
    used because it cannot pick the ``model.visual.`` sub-tree out of a full checkpoint.
    """
    from safetensors import safe_open
    from transformers.initialization import no_init_weights
    from transformers.models.qwen3_vl.modeling_qwen3_vl import Qwen3VLVisionModel

    path = Path(path)
    _check_files(path)
    with no_init_weights():  # every persistent tensor is overwritten below; skip the random init
        model = Qwen3VLVisionModel(_vision_config(path))
    wanted = list(model.state_dict())
    files = _tensor_files(path)
    prefix = next((p for p in _TOWER_PREFIXES if all(p + k in files for k in wanted)), None)
    if prefix is None:
        absent = [k for k in wanted if "model.visual." + k not in files][:3]
        raise ValueError(
            f"qwen3_vl_vision: {path} does not hold the vision tower's tensors under any of {list(_TOWER_PREFIXES)} "
            f"(e.g. model.visual.{absent[0]} is absent; {len(files)} tensors found)"
        )
    by_file: dict[Path, list[str]] = {}
    for k in wanted:
        by_file.setdefault(files[prefix + k], []).append(k)
    state: dict[str, torch.Tensor] = {}
    for file, keys in by_file.items():
        if not file.is_file():
            raise FileNotFoundError(
                f"qwen3_vl_vision: shard {file} listed in {path / 'model.safetensors.index.json'} is missing"
            )
        with safe_open(str(file), framework="pt") as f:
            state.update({k: f.get_tensor(prefix + k) for k in keys})
    model.load_state_dict({k: v.float() for k, v in state.items()}, strict=True)
    return model


def _processor(path: Path | None, vision_cfg: Any, cfg: QwenVisionConfig) -> Any:
    from transformers.models.qwen2_vl.image_processing_pil_qwen2_vl import Qwen2VLImageProcessorPil

    if path is not None and (path / "preprocessor_config.json").is_file():
        proc = Qwen2VLImageProcessorPil.from_pretrained(str(path))
    else:
        factor = vision_cfg.patch_size * vision_cfg.spatial_merge_size
        proc = Qwen2VLImageProcessorPil(
            patch_size=vision_cfg.patch_size,
            merge_size=vision_cfg.spatial_merge_size,
            temporal_patch_size=vision_cfg.temporal_patch_size,
            image_mean=list(QWEN3_VL_IMAGE_MEAN),
            image_std=list(QWEN3_VL_IMAGE_STD),
            # the tiny tower keeps small images at their size; real checkpoints upscale to >= 256x256 as released
            size={
                "shortest_edge": factor * factor if cfg.tiny else QWEN3_VL_MIN_PIXELS,
                "longest_edge": QWEN3_VL_MAX_PIXELS,
            },
        )
    if cfg.min_pixels is not None:
        proc.size.shortest_edge = cfg.min_pixels
    if cfg.max_pixels is not None:
        proc.size.longest_edge = cfg.max_pixels
    ours = (vision_cfg.patch_size, vision_cfg.spatial_merge_size, vision_cfg.temporal_patch_size)
    theirs = (proc.patch_size, proc.merge_size, proc.temporal_patch_size)
    if ours != theirs:
        raise ValueError(
            f"qwen3_vl_vision: {path}/preprocessor_config.json has (patch_size, merge_size, temporal_patch_size) "
            f"{theirs} but the vision config has {ours}"
        )
    return proc


class QwenVisionEncoder(FoundationEncoder):
    """Frozen Qwen3-VL vision tower: ``encode(rgb [H, W, 3] uint8) -> [H, W, d_f]`` float32."""

    name = "qwen3_vl_vision"

    def __init__(self, model: Any, processor: Any, cfg: QwenVisionConfig) -> None:
        super().__init__()
        if cfg.feature not in ("merged", "hidden"):
            raise ValueError(f"qwen3_vl_vision: feature must be 'merged' or 'hidden', got {cfg.feature!r}")
        if (
            not isinstance(getattr(torch, cfg.dtype, None), torch.dtype)
            or not getattr(torch, cfg.dtype).is_floating_point
        ):
            raise ValueError(f"qwen3_vl_vision: dtype {cfg.dtype!r} is not a torch floating-point dtype name")
        self.cfg = cfg
        self.model = model.to(device=cfg.device, dtype=getattr(torch, cfg.dtype))
        self.processor = processor
        self.merge = model.config.spatial_merge_size
        self.d_f = model.config.out_hidden_size if cfg.feature == "merged" else model.config.hidden_size
        self.freeze()

    def token_grid(self, rgb_HW3: np.ndarray) -> torch.Tensor:
        """The tower's tokens on their grid, ``[h, w, d_f]`` float32 (``h, w`` per patch or merged patch)."""
        batch = self.processor(images=rgb_HW3, input_data_format="channels_last", return_tensors="pt")
        pixels = batch["pixel_values"].to(device=self.cfg.device, dtype=getattr(torch, self.cfg.dtype))
        grid_thw = batch["image_grid_thw"].to(self.cfg.device)
        out = self.model(pixels, grid_thw=grid_thw)
        _, gh, gw = (int(v) for v in grid_thw[0])
        m = self.merge
        if self.cfg.feature == "merged":
            return out.pooler_output.float().reshape(gh // m, gw // m, self.d_f)
        # patches arrive in merge-window order (h/m, w/m, m, m); put them back in raster order
        tokens = out.last_hidden_state.float().reshape(gh // m, gw // m, m, m, self.d_f)
        return tokens.permute(0, 2, 1, 3, 4).reshape(gh, gw, self.d_f)

    def _encode(self, rgb_HW3: np.ndarray, out_hw: tuple[int, int]) -> torch.Tensor:
        grid_hwC = self.token_grid(rgb_HW3)
        # the resized image spans the whole original view, so token k covers output rows [k * S, (k + 1) * S)
        sy, sx = out_hw[0] / grid_hwC.shape[0], out_hw[1] / grid_hwC.shape[1]
        return upsample_grid(grid_hwC, out_hw, (sy / 2 - 0.5, sx / 2 - 0.5), (sy, sx))

    def valid_mask(self, H: int, W: int, out_hw: tuple[int, int] | None = None) -> torch.Tensor:
        """All pixels: the tower describes the whole image."""
        return torch.ones((H, W) if out_hw is None else tuple(out_hw), dtype=torch.bool)


@register("encoder", "qwen3_vl_vision")
def build_qwen3_vl_vision(cfg: QwenVisionConfig | EncoderSettings | None = None) -> QwenVisionEncoder:
    """The tower from ``cfg.path``, or the tiny random flavor with ``tiny=True``."""
    if isinstance(cfg, EncoderSettings):  # d_f is the checkpoint's
        cfg = QwenVisionConfig(path=cfg.path, tiny=cfg.tiny)
    cfg = QwenVisionConfig() if cfg is None else cfg
    if cfg.tiny:
        from transformers.models.qwen3_vl.modeling_qwen3_vl import Qwen3VLVisionModel

        vision_cfg = tiny_vision_config()
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(cfg.seed)
            model = Qwen3VLVisionModel(vision_cfg)
        return QwenVisionEncoder(model, _processor(None, vision_cfg, cfg), cfg)
    if cfg.path is None:
        raise FileNotFoundError(
            f"qwen3_vl_vision: no checkpoint directory given (QwenVisionConfig.path is None); expected a local "
            f"directory with {EXPECTED_FILES}, or tiny=True"
        )
    path = Path(cfg.path)
    model = load_vision_tower(path)
    return QwenVisionEncoder(model, _processor(path, model.config, cfg), cfg)
