"""``llm/qwen3_vl``: the world model's LLM, transformers' ``Qwen3VLForConditionalGeneration`` (``tiny`` on CPU).

Sec. Scene Understanding with Gaussian World Tokens. ``WorldLLM`` holds the model, its tokenizer and image
processor and adds what the paper needs on top:

- Gaussian world tokens Z_G enter through a forward hook on the input embedding table (``inject``): the rows of
  the ``<|gauss_pad|>`` slots are replaced by ``z_BFH``, so the model's own path (image scatter, M-RoPE, deepstack,
  KV cache in ``generate``) stays untouched. The slots are text-type tokens for M-RoPE: they get 1-D positions
  right after the last image's 3-D block, like the instruction that follows them.
- ``loss`` is the prefix-LM objective (Eq. L_LM) via the model's shifted cross-entropy on response labels;
- ``generate`` decodes greedily, batched on left-padded prompts, stopping at ``<|im_end|>``.

Full runs load a LOCAL checkpoint directory (``from_pretrained``); ``tiny`` builds a random model of the same
classes (text 2 layers x 64, the encoder module's tiny vision tower) with a BPE tokenizer trained on the corpus.
transformers is imported when a model is built, so looking variants up stays cheap.

Legend: B batch rows, F Gaussian tokens per row (K_f), H LLM hidden size, L sequence length, M image tokens.
"""

from __future__ import annotations

import contextlib
import hashlib
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from model_zoo.config import LLMConfig  # torch-free, so config composition never loads torch
from model_zoo.encoders.qwen3_vl_vision import QwenVisionConfig, _processor, tiny_vision_config
from model_zoo.llm.text import (
    GAUSS_PAD,
    GAUSS_PLACEHOLDER,
    IGNORE_INDEX,
    IM_END,
    IMAGE_PAD,
    PAD,
    VIDEO_PAD,
    VISION_END,
    VISION_START,
    EncodedSample,
    encode_sample,
    train_tiny_tokenizer,
)
from model_zoo.lru import LRU
from model_zoo.registry import register

EXPECTED_FILES = (
    "config.json, model.safetensors (or model.safetensors.index.json with its shards), tokenizer.json (or vocab.json "
    "and merges.txt); preprocessor_config.json optional"
)
PROCESSED_BYTES = 256 * 2**20
"""What ``WorldLLM`` keeps of processed images (``pixel_values`` rows by image content) per model."""


def _check_dir(path: Path) -> None:
    if not path.is_dir():
        raise FileNotFoundError(f"llm/qwen3_vl: checkpoint directory {path} does not exist; expected {EXPECTED_FILES}")
    missing = [] if (path / "config.json").is_file() else ["config.json"]
    if not (path / "model.safetensors").is_file() and not (path / "model.safetensors.index.json").is_file():
        missing.append("model.safetensors (or model.safetensors.index.json)")
    if not (path / "tokenizer.json").is_file() and not all((path / f).is_file() for f in ("vocab.json", "merges.txt")):
        missing.append("tokenizer.json (or vocab.json and merges.txt)")
    if missing:
        raise FileNotFoundError(
            f"llm/qwen3_vl: checkpoint directory {path} lacks {', '.join(missing)}; expected {EXPECTED_FILES}"
        )


def _dtype(name: str) -> torch.dtype:
    dtype = getattr(torch, name, None)
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise ValueError(f"llm/qwen3_vl: dtype {name!r} is not a torch floating-point dtype name")
    return dtype


def add_gauss_token(model: Any, tokenizer: Any) -> int:
    """Id of ``<|gauss_pad|>``, added to ``tokenizer`` as a special token if absent; grows the embeddings if needed.

    Released Qwen tables are padded past the tokenizer (151936 rows for ~151670 tokens), so the new id usually
    has a row already and nothing is resized; the table is never shrunk.
    """
    from tokenizers import AddedToken

    if GAUSS_PAD not in tokenizer.get_vocab():
        tokenizer.add_tokens([AddedToken(GAUSS_PAD, special=True, normalized=False)], special_tokens=True)
    gauss_id = tokenizer.convert_tokens_to_ids(GAUSS_PAD)
    if gauss_id >= model.get_input_embeddings().num_embeddings:
        model.resize_token_embeddings(gauss_id + 1, mean_resizing=True)
    return gauss_id


class WorldLLM:
    """Qwen3-VL with Gaussian world-token slots: ``.model``, ``.tokenizer``, ``.image_processor``."""

    def __init__(self, model: Any, tokenizer: Any, image_processor: Any, cfg: LLMConfig) -> None:
        self.model = model
        self.tokenizer = tokenizer
        self.image_processor = image_processor
        self.cfg = cfg
        self._processed_lru: LRU[tuple[torch.Tensor, torch.Tensor]] = LRU(
            nbytes=PROCESSED_BYTES, size=lambda v: v[0].nbytes
        )
        self.gauss_token_id = add_gauss_token(model, tokenizer)
        ids = {t: tokenizer.convert_tokens_to_ids(t) for t in (PAD, IM_END, IMAGE_PAD, VISION_START, VISION_END)}
        if ids[IMAGE_PAD] != model.config.image_token_id:
            raise ValueError(
                f"llm/qwen3_vl: tokenizer has {IMAGE_PAD} = {ids[IMAGE_PAD]} but the model config says "
                f"image_token_id = {model.config.image_token_id}"
            )
        self.pad_token_id = ids[PAD]
        self.eos_token_id = ids[IM_END]
        self.image_token_id = ids[IMAGE_PAD]
        # tokens only the prompt builder may place: generating one would break the slot bookkeeping
        self._prompt_only_ids = sorted(
            {self.gauss_token_id, ids[IMAGE_PAD], ids[VISION_START], ids[VISION_END], model.config.video_token_id}
        )

    # ------------------------------------------------------------------ construction, persistence

    @classmethod
    def from_pretrained(cls, path: str | Path, cfg: LLMConfig | None = None) -> WorldLLM:
        """Model, tokenizer and image processor from the local directory ``path`` (never downloaded).

        ``cfg=None`` keeps the saved processor's pixel bound and loads float32; a ``cfg`` sets
        ``image_max_pixels``, ``dtype`` and ``max_length``.
        """
        from transformers import AutoTokenizer, Qwen3VLForConditionalGeneration

        path = Path(path)
        _check_dir(path)
        model = Qwen3VLForConditionalGeneration.from_pretrained(
            str(path), dtype=_dtype(cfg.dtype if cfg else "float32"), local_files_only=True
        )
        tokenizer = AutoTokenizer.from_pretrained(str(path), local_files_only=True)
        proc_cfg = QwenVisionConfig(path=str(path), max_pixels=cfg.image_max_pixels if cfg else None)
        processor = _processor(path, model.config.vision_config, proc_cfg)
        cfg = replace(cfg or LLMConfig(image_max_pixels=processor.size.longest_edge), path=str(path), tiny=False)
        return cls(model.eval(), tokenizer, processor, cfg)

    def save(self, path: str | Path) -> None:
        """``save_pretrained`` of model, tokenizer and image processor into ``path`` (``from_pretrained`` reads it)."""
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        self.model.save_pretrained(str(path))
        self.tokenizer.save_pretrained(str(path))
        self.image_processor.save_pretrained(str(path))

    # ------------------------------------------------------------------ properties, inputs

    @property
    def hidden_size(self) -> int:
        """H: width of the LLM's token embeddings (what Z_G must have)."""
        return int(self.model.config.text_config.hidden_size)

    @property
    def device(self) -> torch.device:
        return next(self.model.parameters()).device

    @property
    def dtype(self) -> torch.dtype:
        return self.model.get_input_embeddings().weight.dtype

    def encode(
        self,
        *,
        sample_id: str,
        instruction: str,
        answer: str | None,
        image_tokens: Sequence[int],
        k_f: int,
        gaussian: bool,
    ) -> EncodedSample:
        """``encode_sample`` with this model's tokenizer and ``cfg.max_length``."""
        return encode_sample(
            self,
            sample_id=sample_id,
            instruction=instruction,
            answer=answer,
            image_tokens=image_tokens,
            k_f=k_f,
            gaussian=gaussian,
            max_length=self.cfg.max_length,
        )

    def image_inputs(
        self, images: Sequence[Sequence[np.ndarray]]
    ) -> tuple[torch.Tensor | None, torch.Tensor | None, list[list[int]]]:
        """Per-sample image lists (uint8 ``[H, W, 3]``) -> ``pixel_values``, ``image_grid_thw`` and token counts.

        All images of the batch go through the processor in order (sample by sample); ``n_tokens[b][i]`` is the
        number of ``<|image_pad|>`` slots image ``i`` of sample ``b`` needs. No images -> ``(None, None, [[]...])``.
        """
        flat = []
        for b, views in enumerate(images):
            for i, img in enumerate(views):
                if not isinstance(img, np.ndarray) or img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
                    what = f"{img.dtype} {img.shape}" if isinstance(img, np.ndarray) else type(img).__name__
                    raise ValueError(f"llm/qwen3_vl: sample {b} image {i} must be uint8 [H, W, 3], got {what}")
                flat.append(img)
        if not flat:
            return None, None, [[] for _ in images]
        per_image = [self._processed(img) for img in flat]
        pixel_values = torch.cat([p for p, _ in per_image])
        grid_thw = torch.cat([g for _, g in per_image])
        counts = (grid_thw.prod(-1) // self.model.config.vision_config.spatial_merge_size**2).tolist()
        it = iter(counts)
        return pixel_values, grid_thw, [[next(it) for _ in views] for views in images]

    def _processed(self, img: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """The processor's ``pixel_values`` rows and ``image_grid_thw`` row of one image, kept by the image's content
        (an LRU of ``PROCESSED_BYTES``): training steps see the same camera views again and again, and the processor
        treats each image of a batch alone, so a batch's inputs are its images' rows concatenated."""
        key = (img.shape, hashlib.blake2b(np.ascontiguousarray(img).data, digest_size=16).digest())

        def process() -> tuple[torch.Tensor, torch.Tensor]:
            out = self.image_processor(images=[img], input_data_format="channels_last", return_tensors="pt")
            return out["pixel_values"], out["image_grid_thw"]

        return self._processed_lru.get(key, process)

    def image_features(self, pixel_values: torch.Tensor, image_grid_thw: torch.Tensor) -> Any:
        """The vision tower's output on a batch's images (merged tokens and deepstack features per image): what the
        LLM's forward computes from ``pixel_values``, for a caller that needs the tokens too (``image_features=``
        of ``forward`` and ``loss`` then skips the tower's second pass)."""
        return self.model.get_image_features(pixel_values.to(self.device), image_grid_thw.to(self.device))

    def image_tokens(
        self, pixel_values: torch.Tensor, image_grid_thw: torch.Tensor, features: Any = None
    ) -> list[torch.Tensor]:
        """The vision tower's merged tokens per image, ``[M_i, H]`` (what the LLM consumes; Y_I for L_KL), from
        ``features`` (``image_features``) when given."""
        out = features if features is not None else self.image_features(pixel_values, image_grid_thw)
        return list(out.pooler_output)

    def text_embeddings(self, input_ids: torch.Tensor) -> torch.Tensor:
        """``[B, L, H]``: the input embedding table looked up at ``input_ids`` (no Gaussian injection)."""
        return self.model.get_input_embeddings()(input_ids.to(self.device))

    # ------------------------------------------------------------------ Gaussian world tokens

    @contextlib.contextmanager
    def inject(self, z_BFH: torch.Tensor | None) -> Iterator[None]:
        """Inside, every embedding lookup that meets ``<|gauss_pad|>`` slots puts ``z_BFH[b]`` in row b's slots.

        Each row must hold exactly F slots (lookups without any slot, e.g. decode steps, pass through). With
        ``z_BFH=None`` a lookup that meets slots is an error rather than silently using the placeholder's row.
        """
        if z_BFH is not None and (z_BFH.ndim != 3 or z_BFH.shape[-1] != self.hidden_size):
            raise ValueError(f"llm/qwen3_vl: z_BFH must be [B, F, {self.hidden_size}], got {tuple(z_BFH.shape)}")
        gauss_id = self.gauss_token_id

        def hook(module: Any, args: tuple, kwargs: dict, out: torch.Tensor) -> torch.Tensor | None:
            ids = args[0] if args else kwargs["input"]
            if ids.ndim != 2:  # e.g. the scalar placeholder lookups of get_placeholder_mask
                return None
            slots_BL = ids == gauss_id
            if not bool(slots_BL.any()):
                return None
            counts = slots_BL.sum(1).tolist()
            if z_BFH is None:
                raise ValueError(
                    f"llm/qwen3_vl: rows hold {counts} {GAUSS_PAD} slots but no Gaussian tokens were given"
                )
            B, F, _ = z_BFH.shape
            if ids.shape[0] != B or any(c != F for c in counts):
                raise ValueError(
                    f"llm/qwen3_vl: z_BFH is [{B}, {F}, H] but the {ids.shape[0]} rows hold {counts} {GAUSS_PAD} "
                    f"slots (each row needs exactly {F})"
                )
            # masked_scatter fills row-major, so row b's slots take z_BFH[b] in order; differentiable in z
            return out.masked_scatter(slots_BL.unsqueeze(-1), z_BFH.to(device=out.device, dtype=out.dtype))

        handle = self.model.get_input_embeddings().register_forward_hook(hook, with_kwargs=True)
        try:
            yield
        finally:
            handle.remove()

    # ------------------------------------------------------------------ forward, loss, generation

    def _inputs(
        self,
        batch: dict[str, torch.Tensor],
        z_BFH: torch.Tensor | None,
        pixel_values: torch.Tensor | None,
        image_grid_thw: torch.Tensor | None,
        image_features: Any = None,
    ) -> dict[str, Any]:
        dev = self.device
        ids = batch["input_ids"].to(dev)
        if z_BFH is not None and not bool((ids == self.gauss_token_id).any()):
            raise ValueError(
                f"llm/qwen3_vl: Gaussian tokens were given but the batch has no {GAUSS_PAD} slots "
                "(encoded with gaussian=False?)"
            )
        n_slots = int((ids == self.image_token_id).sum())
        n_feats = 0
        if image_grid_thw is not None:
            n_feats = int((image_grid_thw.prod(-1) // self.model.config.vision_config.spatial_merge_size**2).sum())
        if (pixel_values is None) != (image_grid_thw is None) or n_slots != n_feats:
            raise ValueError(
                f"llm/qwen3_vl: the batch holds {n_slots} {IMAGE_PAD} slots but the images give {n_feats} tokens "
                f"(pixel_values {'absent' if pixel_values is None else 'given'}, image_grid_thw "
                f"{'absent' if image_grid_thw is None else 'given'})"
            )
        # stale deltas from an earlier generate would shift positions of an inputs_embeds-only call
        getattr(self.model, "get_base_model", lambda: self.model)().model.rope_deltas = None
        inputs = {"input_ids": ids, "attention_mask": batch["attention_mask"].to(dev)}
        if pixel_values is not None:
            inputs |= {
                "image_grid_thw": image_grid_thw.to(dev),
                # M-RoPE: image slots (1) get 3-D grid positions, everything else (0) incl. Gaussian slots 1-D ones
                "mm_token_type_ids": (ids == self.image_token_id).int(),
            }
            if image_features is None:
                inputs["pixel_values"] = pixel_values.to(dev)
            else:  # the tower's output on these pixel_values, computed once by the caller
                inputs["mm_encoder_outputs"] = {"image": image_features}
        return inputs

    def forward(
        self,
        batch: dict[str, torch.Tensor],
        z_BFH: torch.Tensor | None = None,
        pixel_values: torch.Tensor | None = None,
        image_grid_thw: torch.Tensor | None = None,
        with_labels: bool = False,
        output_hidden_states: bool = False,
        image_features: Any = None,
    ) -> Any:
        """The model's ``CausalLMOutputWithPast`` on a collated batch (``.loss`` with ``with_labels``);
        ``image_features``: ``image_features(pixel_values, image_grid_thw)`` already computed (the same output)."""
        inputs = self._inputs(batch, z_BFH, pixel_values, image_grid_thw, image_features)
        if with_labels:
            inputs["labels"] = batch["labels"].to(self.device)
        with self.inject(z_BFH):
            return self.model(**inputs, output_hidden_states=output_hidden_states)

    @torch.no_grad()
    def hidden_states(
        self,
        batch: dict[str, torch.Tensor],
        z_BFH: torch.Tensor | None = None,
        pixel_values: torch.Tensor | None = None,
        image_grid_thw: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """``[B, L, H]`` last-layer hidden states of the prompt (the generation branch's C_L = Phi_LLM(Z_G, q))."""
        return self.forward(batch, z_BFH, pixel_values, image_grid_thw, output_hidden_states=True).hidden_states[-1]

    def loss(
        self,
        batch: dict[str, torch.Tensor],
        z_BFH: torch.Tensor | None = None,
        pixel_values: torch.Tensor | None = None,
        image_grid_thw: torch.Tensor | None = None,
        image_features: Any = None,
    ) -> torch.Tensor:
        """Eq. L_LM: next-token cross-entropy on the response tokens, averaged over them (the model's shift).

        The paper sums over a sample's tokens and averages over samples; the token mean differs by a
        length-dependent scale only. ``image_features``: as ``forward``'s.
        """
        if not bool((batch["labels"] != -100).any()):
            raise ValueError("llm/qwen3_vl: the batch has no response tokens (all labels are -100)")
        out = self.forward(batch, z_BFH, pixel_values, image_grid_thw, with_labels=True, image_features=image_features)
        return out.loss

    @torch.no_grad()
    def generate(
        self,
        batch: dict[str, torch.Tensor],
        z_BFH: torch.Tensor | None = None,
        pixel_values: torch.Tensor | None = None,
        image_grid_thw: torch.Tensor | None = None,
        max_new_tokens: int = 64,
    ) -> list[str]:
        """Greedy answers for left-padded prompts (``encode(answer=None)``, ``collate(padding_side="left")``)."""
        from transformers import GenerationConfig

        if not bool(batch["attention_mask"][:, -1].all()):
            raise ValueError("llm/qwen3_vl: generate needs left-padded prompts (collate(..., padding_side='left'))")
        inputs = self._inputs(batch, z_BFH, pixel_values, image_grid_thw)
        gen = GenerationConfig(
            max_new_tokens=max_new_tokens,
            do_sample=False,
            eos_token_id=self.eos_token_id,
            pad_token_id=self.pad_token_id,
            suppress_tokens=self._prompt_only_ids,
        )
        was_training = self.model.training
        self.model.eval()
        try:
            # the prefill lookup holds the slots; decode steps look up one new token each and pass the hook
            with self.inject(z_BFH):
                out = self.model.generate(**inputs, generation_config=gen)
        finally:
            self.model.train(was_training)
        new = out[:, inputs["input_ids"].shape[1] :]
        return self.tokenizer.batch_decode(new, skip_special_tokens=True)


def _tiny_model(cfg: LLMConfig, tokenizer: Any) -> Any:
    from transformers import Qwen3VLConfig, Qwen3VLForConditionalGeneration
    from transformers.models.qwen3_vl import Qwen3VLTextConfig

    if cfg.hidden_size % cfg.num_heads or (cfg.hidden_size // cfg.num_heads) % 8:
        raise ValueError(
            f"llm/qwen3_vl tiny: hidden_size {cfg.hidden_size} / num_heads {cfg.num_heads} must be a multiple of 8 "
            "(M-RoPE splits the rotary half into t/h/w sections)"
        )
    head_dim = cfg.hidden_size // cfg.num_heads
    half = head_dim // 2
    tid = tokenizer.convert_tokens_to_ids
    text = Qwen3VLTextConfig(
        vocab_size=len(tokenizer),
        hidden_size=cfg.hidden_size,
        intermediate_size=cfg.intermediate_size,
        num_hidden_layers=cfg.num_layers,
        num_attention_heads=cfg.num_heads,
        num_key_value_heads=cfg.num_kv_heads,
        head_dim=head_dim,
        max_position_embeddings=max(4096, 4 * cfg.max_length),
        pad_token_id=tid(PAD),
        # Qwen3-VL's interleaved M-RoPE, sections scaled from the released [24, 20, 20] of 64
        rope_parameters={
            "rope_type": "default",
            "rope_theta": 5_000_000.0,
            "mrope_section": [half - 2 * (half * 5 // 16), half * 5 // 16, half * 5 // 16],
            "mrope_interleaved": True,
        },
    )
    vision = tiny_vision_config()
    vision.out_hidden_size = cfg.hidden_size  # the merger projects straight into the LLM width
    config = Qwen3VLConfig(
        text_config=text,
        vision_config=vision,
        image_token_id=tid(IMAGE_PAD),
        video_token_id=tid(VIDEO_PAD),
        vision_start_token_id=tid(VISION_START),
        vision_end_token_id=tid(VISION_END),
    )
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(cfg.seed)
        model = Qwen3VLForConditionalGeneration(config)
    model.generation_config.eos_token_id = tid(IM_END)
    model.generation_config.pad_token_id = tid(PAD)
    return model.to(_dtype(cfg.dtype)).eval()


PRETRAIN_ON = ("text", "instructions")


@register("llm", "qwen3_vl")
def build_qwen3_vl(
    cfg: LLMConfig | None = None,
    corpus: Iterable[str] | None = None,
    instructions: Sequence[tuple[str, str]] | None = None,
) -> WorldLLM:
    """The checkpoint at ``cfg.path``, or with ``tiny=True`` a random model + a tokenizer trained on ``corpus``, warmed
    up as ``cfg.pretrain_on`` says (``instructions``: the (instruction, answer) pairs it reads)."""
    cfg = LLMConfig() if cfg is None else cfg
    if cfg.tiny:
        if corpus is None:
            raise ValueError(
                "llm/qwen3_vl tiny: a text corpus is required to train the tiny BPE tokenizer "
                "(build('llm', 'qwen3_vl', cfg, corpus=[...]))"
            )
        if cfg.pretrain_on not in PRETRAIN_ON:
            raise ValueError(f"model.llm.pretrain_on: unknown '{cfg.pretrain_on}' (one of {list(PRETRAIN_ON)})")
        if cfg.pretrain_steps > 0 and cfg.pretrain_on == "instructions" and not instructions:
            raise ValueError(
                "llm/qwen3_vl tiny: model.llm.pretrain_on=instructions needs the (instruction, answer) pairs "
                "(build('llm', 'qwen3_vl', cfg, corpus=[...], instructions=[...]))"
            )
        corpus = list(corpus)
        tokenizer = train_tiny_tokenizer(corpus, cfg.vocab_size)
        model = _tiny_model(cfg, tokenizer)
        proc_cfg = QwenVisionConfig(tiny=True, max_pixels=cfg.image_max_pixels)
        llm = WorldLLM(model, tokenizer, _processor(None, model.config.vision_config, proc_cfg), cfg)
        if cfg.pretrain_steps > 0:
            args = (cfg.pretrain_steps, cfg.pretrain_lr, cfg.pretrain_batch_size, cfg.seed)
            if cfg.pretrain_on == "instructions":
                pretrain_on_instructions(llm, list(instructions or []), *args)
            else:
                pretrain_on_text(llm, corpus, *args)
        return llm
    if cfg.path is None:
        raise FileNotFoundError(
            f"llm/qwen3_vl: no checkpoint directory given (LLMConfig.path is None); expected a local directory with "
            f"{EXPECTED_FILES}, or tiny=True"
        )
    return WorldLLM.from_pretrained(cfg.path, cfg)


def pretrain_on_text(
    llm: WorldLLM, corpus: list[str], steps: int, lr: float, batch_size: int, seed: int
) -> list[float]:
    """Next-token training of every parameter on ``corpus`` (documents ended by ``<|endoftext|>``); returns the
    losses. Deterministic for a given corpus and seed."""
    tok = llm.tokenizer
    docs = [[*ids, llm.pad_token_id] for ids in tok(corpus, add_special_tokens=False)["input_ids"] if ids]
    if not docs:
        raise ValueError("llm/qwen3_vl tiny: the pre-training corpus has no text")
    return _pretrain(llm, [(d, d) for d in docs], steps, lr, batch_size, seed)


def pretrain_on_instructions(
    llm: WorldLLM, pairs: list[tuple[str, str]], steps: int, lr: float, batch_size: int, seed: int
) -> list[float]:
    """Instruction tuning of every parameter on (instruction, answer) pairs in the chat template ``encode`` builds,
    text only (the ``<gauss>`` placeholder reads "the scene"), loss on the answer; returns the losses. Deterministic
    for given pairs and seed."""
    docs = []
    for i, (instruction, answer) in enumerate(pairs):
        enc = llm.encode(
            sample_id=f"pretrain/{i}",
            instruction=instruction.replace(GAUSS_PLACEHOLDER, "the scene"),
            answer=answer,
            image_tokens=[],
            k_f=0,
            gaussian=False,
        )
        docs.append((enc.input_ids, enc.labels))
    if not docs:
        raise ValueError("llm/qwen3_vl tiny: no (instruction, answer) pairs to pre-train on")
    return _pretrain(llm, docs, steps, lr, batch_size, seed)


def _pretrain(
    llm: WorldLLM, docs: list[tuple[list[int], list[int]]], steps: int, lr: float, batch_size: int, seed: int
) -> list[float]:
    """Full-parameter AdamW steps on random batches of (input ids, labels) documents, right-padded."""
    model = llm.model
    gen = torch.Generator().manual_seed(seed)
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=0.0)
    losses = []
    model.train()
    for _ in range(steps):
        pick = torch.randint(len(docs), (min(batch_size, len(docs)),), generator=gen).tolist()
        length = max(len(docs[i][0]) for i in pick)
        ids = torch.full((len(pick), length), llm.pad_token_id, dtype=torch.long)
        labels = torch.full_like(ids, IGNORE_INDEX)
        mask = torch.zeros_like(ids)
        for b, i in enumerate(pick):
            n = len(docs[i][0])
            ids[b, :n] = torch.tensor(docs[i][0])
            labels[b, :n] = torch.tensor(docs[i][1])
            mask[b, :n] = 1
        loss = model(input_ids=ids, attention_mask=mask, labels=labels).loss
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    model.eval()
    return losses
