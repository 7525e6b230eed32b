"""Registers the schemas of ``pipelines`` with gdwm (entry point ``gdwm.plugins``)."""

from __future__ import annotations

from hydra.core.config_store import ConfigStore


def register(cs: ConfigStore) -> None:
    from pipelines.data.gaussiandwm import ReleaseConfig
    from pipelines.data.nuscenes import NuScenesConfig
    from pipelines.data.synth.config import SynthConfig
    from pipelines.distill.config import DistillConfig
    from pipelines.recon.config import ReconstructConfig

    cs.store(group="schema/data", name="synthetic_mini", node=SynthConfig)
    cs.store(group="schema/data", name="nuscenes", node=NuScenesConfig)
    cs.store(group="schema/data", name="gaussiandwm_release", node=ReleaseConfig)
    cs.store(group="schema/stage", name="reconstruct", node=ReconstructConfig)
    cs.store(group="schema/stage", name="distill", node=DistillConfig)
