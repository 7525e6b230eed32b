"""llm (stage 0): the language model every row of a table starts from, built once per ``model.llm`` and dataset.

Tiny flavor (``model.llm.tiny``): a random Qwen3-VL config and a byte-level BPE tokenizer trained on the training
split's QA text, warmed up as ``model.llm.pretrain_on`` says: the CPU stand-in for the released instruction-tuned
checkpoint. Its key holds ``model.llm`` (its seed follows the trial seed unless pinned) and the data, nothing of
the adapter, selector or distillation, so every row of an ablation table trains from the same LLM, built once.
It reads the training split's text only (no image, no Gaussian, no val sample), every training record whether or
not its frame has Gaussians, so it needs no upstream stage. A full run (``tiny: false``) builds nothing: the
tokenizer stage reads ``model.llm.path``.

Output: ``llm/`` (``WorldLLM.save``) for the tiny flavor, and ``metrics.json``.
"""

from __future__ import annotations

import json

from gdwm.api import StageContext, stage
from model_zoo import registry
from model_zoo.config import LLMConfig
from pipelines.data.reader import GSQADataset
from pipelines.understanding.data import instruction_pairs, load_samples, training_corpus
from pipelines.understanding.model import LLM_DIR


def _needs(config: dict) -> dict[str, str]:
    return (
        {"qa": "the tiny LLM learns its tokenizer and answer formats from the training QA"}
        if config["model.llm"]["tiny"]
        else {}
    )


@stage("llm", "1", config=["model.llm"], resources="cpu", needs=_needs)
def llm(ctx: StageContext) -> dict:
    cfg = LLMConfig(**ctx.cfg("model.llm"))
    metrics = {"built": float(cfg.tiny), "train_texts": 0, "instruction_pairs": 0}
    if cfg.tiny:
        train, _ = load_samples(GSQADataset(ctx.data_root), "train", {}, need_gaussians=False)
        if not train:
            raise ValueError(f"llm: the dataset at {ctx.data_root} has no training QA to build the tiny LLM from")
        corpus, pairs = training_corpus(train), instruction_pairs(train)
        registry.build("llm", cfg.name, cfg, corpus=corpus, instructions=pairs).save(ctx.out_dir / LLM_DIR)
        metrics |= {"train_texts": len(corpus), "instruction_pairs": len(pairs)}
    ctx.tracker.log_metrics({k: float(v) for k, v in metrics.items()})
    (ctx.out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2, sort_keys=True))
    return metrics
