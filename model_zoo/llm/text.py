"""Prompt side of the world LLM: special tokens, the tiny BPE tokenizer, X_in = Concat(V, Z_G, T), and collation.

Sec. Scene Understanding with Gaussian World Tokens: the K_f Gaussian world tokens sit in dedicated
``<|gauss_pad|>`` slots between the image tokens and the instruction, and the LM loss covers the response only
(Eq. L_LM, prefix-LM). Template (Qwen chat format)::

    <|im_start|>user\\n [<|vision_start|> <|image_pad|> x n_i <|vision_end|>]* <|gauss_pad|> x K_f instruction
    <|im_end|>\\n<|im_start|>assistant\\n answer <|im_end|>

Pieces are tokenized separately and concatenated: special tokens split the text anyway, so this equals tokenizing
the whole string, and it tells us exactly where the instruction tokens are.

Legend: B batch rows, L sequence length.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import torch

log = logging.getLogger(__name__)

PAD = "<|endoftext|>"
IM_START = "<|im_start|>"
IM_END = "<|im_end|>"
VISION_START = "<|vision_start|>"
VISION_END = "<|vision_end|>"
IMAGE_PAD = "<|image_pad|>"
VIDEO_PAD = "<|video_pad|>"
GAUSS_PAD = "<|gauss_pad|>"
# Qwen's own special tokens (video_pad only so the model config names a real id), then ours.
QWEN_SPECIAL_TOKENS = (PAD, IM_START, IM_END, VISION_START, VISION_END, IMAGE_PAD, VIDEO_PAD)
SPECIAL_TOKENS = (*QWEN_SPECIAL_TOKENS, GAUSS_PAD)

GAUSS_PLACEHOLDER = "<gauss>"
"""Literal placeholder in instructions, e.g. ``Based on <gauss>, please locate ...``."""
GAUSS_WORDS = "the Gaussian scene tokens"
IMAGE_WORDS = "the images"
IGNORE_INDEX = -100
"""Label of tokens without loss (the prefix, padding); what ``torch.nn.functional.cross_entropy`` ignores."""


def train_tiny_tokenizer(corpus: Iterable[str], vocab_size: int, special_tokens: Sequence[str] = SPECIAL_TOKENS) -> Any:
    """A byte-level BPE ``PreTrainedTokenizerFast`` trained on ``corpus`` with Qwen's special tokens and ours.

    Byte-level so any string encodes (no unknown token); ``vocab_size`` is a target, a small corpus yields fewer
    merges. Special tokens take the first ids in ``special_tokens`` order (the first one pads).
    """
    from tokenizers import Tokenizer, decoders, models, pre_tokenizers, trainers
    from transformers import PreTrainedTokenizerFast

    texts = [t for t in corpus if t]
    if not texts:
        raise ValueError("llm/qwen3_vl tiny: the corpus to train the tokenizer on is empty")
    bpe = Tokenizer(models.BPE())
    bpe.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False)
    bpe.decoder = decoders.ByteLevel()
    trainer = trainers.BpeTrainer(
        vocab_size=vocab_size,
        special_tokens=list(special_tokens),
        initial_alphabet=pre_tokenizers.ByteLevel.alphabet(),
        show_progress=False,
    )
    bpe.train_from_iterator(texts, trainer)
    return PreTrainedTokenizerFast(
        tokenizer_object=bpe,
        pad_token=special_tokens[0],
        eos_token=IM_END,
        extra_special_tokens=list(special_tokens[1:]),
    )


@dataclass
class EncodedSample:
    """One tokenized prefix-response pair (Eq. L_LM)."""

    input_ids: list[int]
    """Prefix (images, Gaussian slots, instruction, chat scaffolding) then response."""
    labels: list[int]
    """``IGNORE_INDEX`` on the prefix, the token ids on the response."""
    n_gauss: int
    """Number of ``<|gauss_pad|>`` slots (K_f, or 0 with Gaussian tokens off)."""
    text_positions: list[int]
    """Positions of the instruction tokens (for the pooled instruction embedding)."""
    response_start: int
    """Index of the first response token (= prefix length)."""


def _tokenizer(llm_or_tokenizer: Any) -> Any:
    return getattr(llm_or_tokenizer, "tokenizer", llm_or_tokenizer)


def _ids(tok: Any, text: str) -> list[int]:
    return list(tok.encode(text, add_special_tokens=False)) if text else []


def encode_sample(
    llm_or_tokenizer: Any,
    *,
    sample_id: str,
    instruction: str,
    answer: str | None,
    image_tokens: Sequence[int],
    k_f: int,
    gaussian: bool,
    max_length: int,
) -> EncodedSample:
    """Token ids and labels of X_in = Concat(V, Z_G, T) + answer (Sec. Input Token Construction).

    ``image_tokens`` holds the merged-token count of each image (``WorldLLM.image_inputs``); ``answer=None`` builds
    the generation prompt (ends with ``assistant\\n``). The instruction's ``<gauss>`` placeholder is required with
    ``gaussian=True``; it reads "the Gaussian scene tokens" (or "the images" with Gaussian tokens off) and its K_f
    slots are the ones placed before the instruction. An answer that does not fit ``max_length`` is cut (and the
    closing ``<|im_end|>`` with it, so the model is not taught to stop there); a prefix that does not fit is an error.
    """
    tok = _tokenizer(llm_or_tokenizer)
    for what, text in (("instruction", instruction), ("answer", answer or "")):
        if found := [s for s in SPECIAL_TOKENS if s in text]:
            raise ValueError(
                f"{sample_id}: {what} contains the special token(s) {found}; the prompt builder places them"
            )
    if gaussian:
        if GAUSS_PLACEHOLDER not in instruction:
            raise ValueError(f"{sample_id}: instruction has no <gauss> placeholder but Gaussian tokens are on")
        if k_f <= 0:
            raise ValueError(f"{sample_id}: Gaussian tokens are on but k_f is {k_f}")
    if any(n <= 0 for n in image_tokens):
        raise ValueError(f"{sample_id}: every image needs at least one token, got counts {list(image_tokens)}")
    n_gauss = k_f if gaussian else 0
    text = instruction.replace(GAUSS_PLACEHOLDER, GAUSS_WORDS if gaussian else IMAGE_WORDS)

    sid = tok.convert_tokens_to_ids
    ids = [sid(IM_START), *_ids(tok, "user\n")]
    for n in image_tokens:
        ids += [sid(VISION_START), *[sid(IMAGE_PAD)] * n, sid(VISION_END)]
    ids += [sid(GAUSS_PAD)] * n_gauss
    instr = _ids(tok, text)
    text_positions = list(range(len(ids), len(ids) + len(instr)))
    ids += [*instr, sid(IM_END), *_ids(tok, "\n"), sid(IM_START), *_ids(tok, "assistant\n")]
    prefix = len(ids)
    if prefix > max_length:
        raise ValueError(
            f"{sample_id}: prompt is {prefix} tokens ({sum(image_tokens)} image, {n_gauss} Gaussian, {len(instr)} "
            f"instruction), longer than max_length {max_length}"
        )
    response = [*_ids(tok, answer), sid(IM_END)] if answer is not None else []
    if prefix + len(response) > max_length:
        keep = max_length - prefix
        log.warning(
            "%s: answer cut from %d to %d tokens to fit max_length %d (prompt %d tokens)",
            sample_id,
            len(response) - 1,
            keep,
            max_length,
            prefix,
        )
        response = response[:keep]
    return EncodedSample(
        input_ids=ids + response,
        labels=[IGNORE_INDEX] * prefix + response,
        n_gauss=n_gauss,
        text_positions=text_positions,
        response_start=prefix,
    )


def collate(
    samples: Sequence[EncodedSample], pad_id: int, padding_side: Literal["right", "left"] = "right"
) -> dict[str, torch.Tensor]:
    """Pad to the longest sample: ``input_ids``, ``attention_mask``, ``labels``, ``instruction_mask`` ``[B, L]`` long.

    Right padding for training, left padding for ``generate`` (new tokens follow every prompt's last token).
    ``instruction_mask`` marks the instruction tokens (``text_positions``) wherever the padding put them.
    """
    if padding_side not in ("right", "left"):
        raise ValueError(f"padding_side must be 'right' or 'left', got {padding_side!r}")
    if not samples:
        raise ValueError("collate: no samples")
    L = max(len(s.input_ids) for s in samples)
    out = {k: torch.full((len(samples), L), v, dtype=torch.long) for k, v in _FILL.items()}
    out["input_ids"].fill_(pad_id)
    for b, s in enumerate(samples):
        n = len(s.input_ids)
        off = 0 if padding_side == "right" else L - n
        out["input_ids"][b, off : off + n] = torch.tensor(s.input_ids)
        out["attention_mask"][b, off : off + n] = 1
        out["labels"][b, off : off + n] = torch.tensor(s.labels)
        out["instruction_mask"][b, [off + p for p in s.text_positions]] = 1
    return out


_FILL = {"input_ids": 0, "attention_mask": 0, "labels": IGNORE_INDEX, "instruction_mask": 0}
