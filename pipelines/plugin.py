"""Registers the schemas of ``pipelines`` with gdwm (entry point ``gdwm.plugins``)."""

from __future__ import annotations

from hydra.core.config_store import ConfigStore


def register(cs: ConfigStore) -> None:
    # Config modules only: composing a config must not import torch, transformers or diffusers.
    from model_zoo.config import (
        AlignmentConfig,
        DiffusionConfig,
        FineAdapterConfig,
        LLMConfig,
        ProjectionConfig,
        SelectorConfig,
        register_resolvers,
    )
    from pipelines.data.gaussiandwm import ReleaseConfig
    from pipelines.data.nuinstruct import NuInstructConfig
    from pipelines.data.nuinteract import NuInteractConfig
    from pipelines.data.nuscenes import NuScenesConfig
    from pipelines.data.omnidrive import OmniDriveConfig
    from pipelines.data.synth.config import SynthConfig
    from pipelines.distill.config import DistillConfig
    from pipelines.evaluate.config import EvaluateGenConfig, EvaluateQAConfig
    from pipelines.generation.cli import EditArgs, GenerateArgs
    from pipelines.generation.config import DiffusionStageConfig, VaeStageConfig
    from pipelines.recon.config import ReconstructConfig
    from pipelines.understanding.config import LoraStageConfig, TokenizerStageConfig, WorldConfig

    register_resolvers()
    from gdwm.api import register_callables

    datasets = (SynthConfig, NuScenesConfig, ReleaseConfig, NuInteractConfig, NuInstructConfig, OmniDriveConfig)
    for dataset in datasets:  # the functions gdwm may call for our datasets
        register_callables("data.builder", dataset.builder)
        register_callables("data.planner", dataset.planner)
        register_callables("data.summarizer", dataset.summarizer)
        register_callables("data.checker", dataset.checker)
    cs.store(group="schema/data", name="synthetic_mini", node=SynthConfig)
    cs.store(group="schema/data", name="nuscenes", node=NuScenesConfig)
    cs.store(group="schema/data", name="gaussiandwm_release", node=ReleaseConfig)
    cs.store(group="schema/data", name="nuinteract", node=NuInteractConfig)
    cs.store(group="schema/data", name="nuinstruct", node=NuInstructConfig)
    cs.store(group="schema/data", name="omnidrive", node=OmniDriveConfig)
    cs.store(group="schema/stage", name="reconstruct", node=ReconstructConfig)
    cs.store(group="schema/stage", name="distill", node=DistillConfig)
    cs.store(group="schema/stage", name="tokenizer", node=TokenizerStageConfig)
    cs.store(group="schema/stage", name="lora", node=LoraStageConfig)
    cs.store(group="schema/model", name="world", node=WorldConfig)
    cs.store(group="schema/model", name="selector", node=SelectorConfig)
    cs.store(group="schema/model", name="projection", node=ProjectionConfig)
    cs.store(group="schema/model", name="fine_adapter", node=FineAdapterConfig)
    cs.store(group="schema/model", name="alignment", node=AlignmentConfig)
    cs.store(group="schema/model", name="llm", node=LLMConfig)
    cs.store(group="schema/stage", name="diffusion_vae", node=VaeStageConfig)
    cs.store(group="schema/stage", name="diffusion", node=DiffusionStageConfig)
    cs.store(group="schema/model", name="diffusion", node=DiffusionConfig)
    cs.store(group="schema/stage", name="evaluate_qa", node=EvaluateQAConfig)
    cs.store(group="schema/stage", name="evaluate_gen", node=EvaluateGenConfig)
    cs.store(group="schema/args", name="generate", node=GenerateArgs)
    cs.store(group="schema/args", name="edit", node=EditArgs)
