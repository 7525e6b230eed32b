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


def _resolve(name: str, target: str) -> StageDef:
    where = f"pipeline.stages.{name}._target_"
    try:
        obj: Any = get_object(target)
    except Exception as e:
        raise DagError(f"{where}: cannot import '{target}' ({e})") from e
    if not isinstance(obj, StageDef):
        raise DagError(f"{where}: '{target}' is not a gdwm stage (decorate it with gdwm.stage.stage)")
    if obj.name != name:
        raise DagError(f"{where}: '{target}' declares stage name '{obj.name}', not '{name}'")
    return obj


def load_pipeline(cfg: DictConfig, targets: list[str] | None = None) -> Pipeline:
    """Validate the DAG; with ``targets``, only they and their ancestors are imported and checked."""
    pcfg = cfg.pipeline
    declared = {name: ref._target_ for name, ref in pcfg.stages.items()}
    unknown = [t for t in targets or [] if t not in declared]
    if unknown:
        raise DagError(f"targets {unknown} are not stages of pipeline '{pcfg.name}' (stages: {sorted(declared)})")
    stages: dict[str, StageDef] = {}
    todo = list(targets) if targets else list(declared)
    while todo:
        name = todo.pop(0)
        if name in stages:
            continue
        stages[name] = _resolve(name, declared[name])
        if targets:
            todo += [u for u in stages[name].upstream if u in declared]
    for name, sd in stages.items():
        missing = [u for u in sd.upstream if u not in declared]
        if missing:
            raise DagError(
                f"stage '{name}' needs upstream {missing}, which pipeline '{pcfg.name}' does not define "
                f"(stages: {sorted(declared)})"
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
