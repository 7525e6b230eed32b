"""The pipeline DAG from config (``conf/pipeline/*.yaml``), validated before anything runs."""

from __future__ import annotations

from dataclasses import dataclass, field
from graphlib import CycleError, TopologicalSorter
from typing import Any

from hydra.utils import get_object
from omegaconf import DictConfig, OmegaConf

from gdwm.stage import StageDef


class DagError(Exception):
    """An invalid pipeline: unknown stage, cycle, missing upstream, absent config subtree. Exit 2."""


@dataclass
class StageRef:
    """One stage of a pipeline."""

    _target_: str = "???"
    """Dotted path of the StageDef (the function decorated with ``gdwm.stage.stage``)."""


@dataclass
class PipelineConfig:
    """A DAG of stages (group ``pipeline/``)."""

    name: str = "???"
    """Pipeline name."""
    stages: dict[str, StageRef] = field(default_factory=dict)
    """Stage name -> implementation; edges come from each stage's declared upstream."""


@dataclass
class Pipeline:
    name: str
    stages: dict[str, StageDef]
    order: list[str]
    """Topological order (upstream first, ties by name)."""

    def ancestors(self, targets: list[str]) -> list[str]:
        """``targets`` and everything they need, in topological order."""
        unknown = [t for t in targets if t not in self.stages]
        if unknown:
            raise DagError(f"targets {unknown} are not stages of pipeline '{self.name}' (stages: {self.order})")
        needed: set[str] = set()
        todo = list(targets)
        while todo:
            s = todo.pop()
            if s not in needed:
                needed.add(s)
                todo.extend(self.stages[s].upstream)
        return [s for s in self.order if s in needed]


def _has(cfg: DictConfig, dotted: str) -> bool:
    try:
        return OmegaConf.select(cfg, dotted, throw_on_missing=True) is not None
    except Exception:
        return False


def load_pipeline(cfg: DictConfig) -> Pipeline:
    pcfg = cfg.pipeline
    stages: dict[str, StageDef] = {}
    for name, ref in pcfg.stages.items():
        where = f"pipeline.stages.{name}._target_"
        try:
            obj: Any = get_object(ref._target_)
        except Exception as e:
            raise DagError(f"{where}: cannot import '{ref._target_}' ({e})") from e
        if not isinstance(obj, StageDef):
            raise DagError(f"{where}: '{ref._target_}' is not a gdwm stage (decorate it with gdwm.stage.stage)")
        if obj.name != name:
            raise DagError(f"{where}: '{ref._target_}' declares stage name '{obj.name}', not '{name}'")
        stages[name] = obj
    for name, sd in stages.items():
        missing = [u for u in sd.upstream if u not in stages]
        if missing:
            raise DagError(
                f"stage '{name}' needs upstream {missing}, which pipeline '{pcfg.name}' does not define "
                f"(stages: {sorted(stages)})"
            )
        absent = [k for k in sd.config if not _has(cfg, k)]
        if absent:
            raise DagError(f"stage '{name}' depends on config {absent}, absent from the composed config")
    ts = TopologicalSorter({n: sorted(sd.upstream) for n, sd in sorted(stages.items())})
    try:
        order = list(ts.static_order())
    except CycleError as e:
        raise DagError(f"pipeline '{pcfg.name}' has a cycle: {' -> '.join(e.args[1])}") from e
    return Pipeline(pcfg.name, stages, order)
