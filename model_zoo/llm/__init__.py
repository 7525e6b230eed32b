"""The world model's LLM: ``qwen3_vl`` (transformers Qwen3-VL; ``tiny`` for CPU) and its prompt construction."""

from model_zoo.llm.qwen3_vl import LLMConfig, WorldLLM, add_gauss_token, build_qwen3_vl
from model_zoo.llm.text import (
    GAUSS_PAD,
    GAUSS_PLACEHOLDER,
    IGNORE_INDEX,
    SPECIAL_TOKENS,
    EncodedSample,
    collate,
    encode_sample,
    train_tiny_tokenizer,
)

__all__ = [
    "GAUSS_PAD",
    "GAUSS_PLACEHOLDER",
    "IGNORE_INDEX",
    "SPECIAL_TOKENS",
    "EncodedSample",
    "LLMConfig",
    "WorldLLM",
    "add_gauss_token",
    "build_qwen3_vl",
    "collate",
    "encode_sample",
    "train_tiny_tokenizer",
]
