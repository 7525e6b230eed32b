"""Resource shapes against the cluster's nodes: every launch refuses, before anything starts, a stage whose task,
actor or Ray Train worker group no node (or no set of nodes) can host. Ray itself would leave such work pending
forever.

Nodes come from ``ray.nodes()`` on a live cluster, else from ``cluster.nodes``, else (a local Ray about to start)
one node of ``cluster.num_cpus`` and ``cluster.num_gpus``. A stage of resource class ``cls`` asks
``cluster.resources.<cls>``: per-scene stages and ``cpu``/``gpu``/``eval`` stages need one node holding one
task's ``num_cpus`` and ``num_gpus``; a ``train`` stage with ``num_workers`` > 0 needs the whole worker group placed
at once (Ray Train reserves it as one placement group, spread across nodes as needed); ``num_workers: 0`` runs
in the driver and asks nothing of the cluster.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from omegaconf import DictConfig, OmegaConf


@dataclass(frozen=True)
class Node:
    num_cpus: float
    num_gpus: float
    count: int = 1

    def __str__(self) -> str:
        return f"{_n(self.num_cpus)} CPU, {_n(self.num_gpus)} GPU"

    def fits(self, cpus: float, gpus: float) -> int:
        """How many tasks of ``cpus`` CPUs and ``gpus`` GPUs one such node holds at once."""
        per = [math.floor(self.num_cpus / cpus + 1e-9) if cpus > 0 else math.inf]
        per.append(math.floor(self.num_gpus / gpus + 1e-9) if gpus > 0 else math.inf)
        n = min(per)
        return 10**9 if n == math.inf else int(n)


def _n(x: float) -> str:
    return f"{x:g}"


def live_nodes() -> list[Node] | None:
    """The alive nodes of the connected Ray cluster (None when Ray is not initialised)."""
    import ray

    if not ray.is_initialized():
        return None
    out = []
    for n in ray.nodes():
        if n.get("Alive"):
            r = n.get("Resources", {})
            out.append(Node(float(r.get("CPU", 0)), float(r.get("GPU", 0))))
    return out


def cluster_nodes(cluster: DictConfig | Mapping, live: bool = True) -> list[Node]:
    """The nodes of ``cluster`` (see the module docstring; ``live=False``: never the connected Ray's); [] when
    unknown (a remote cluster without ``nodes``)."""
    live = live_nodes() if live else None
    if live is not None:
        return live
    c = OmegaConf.to_container(cluster, resolve=True) if isinstance(cluster, DictConfig) else dict(cluster)
    if c.get("nodes"):
        return [Node(float(n["num_cpus"]), float(n["num_gpus"]), int(n.get("count", 1))) for n in c["nodes"]]
    if c.get("address") is None:
        return [Node(float(c.get("num_cpus") or os.cpu_count() or 1), float(c.get("num_gpus") or 0))]
    return []


def describe(nodes: Sequence[Node]) -> str:
    return ", ".join(f"{n.count} x {n}" if n.count > 1 else str(n) for n in nodes)


def shape_errors(stages: Mapping[str, str], resources: Mapping[str, Mapping], nodes: Sequence[Node],
                 cluster: str) -> list[str]:  # fmt: skip
    """One line per stage (name -> resource class) whose shape ``nodes`` cannot host, naming the stage, the shape
    and the largest node."""
    if not nodes:
        return []
    largest = max(nodes, key=lambda n: (n.num_gpus, n.num_cpus))
    out = []
    for name, cls in stages.items():
        r = resources.get(cls, {})
        cpus, gpus, workers = float(r.get("num_cpus", 1)), float(r.get("num_gpus", 0)), int(r.get("num_workers", 1))
        shape = f"cluster.resources.{cls}: {_n(cpus)} CPU, {_n(gpus)} GPU"
        if cls == "train" and workers == 0:
            continue  # in the driver
        if cls == "train":
            placeable = sum(min(n.fits(cpus, gpus), 10**9) * n.count for n in nodes)
            if placeable < workers:
                out.append(f"stage '{name}': a Ray Train group of {workers} workers of {shape[shape.index(':') + 2:]} "
                           f"({shape.split(':')[0]}) cannot be placed on cluster '{cluster}': its nodes hold at most "
                           f"{placeable} (nodes: {describe(nodes)}; largest: {largest})")  # fmt: skip
        elif not any(n.fits(cpus, gpus) >= 1 for n in nodes):
            out.append(f"stage '{name}': {shape} per task, which no node of cluster '{cluster}' can host "
                       f"(largest node: {largest})")  # fmt: skip
    return out


# ---- capacity plan (`gdwm sweep --dry-run`) -----------------------------------------------------------------------

GPU_SPEEDUP = 20.0
"""Scaling model: a task that asks for a GPU on the target cluster runs this many times faster than the same task
measured on a cluster that gave it none (a CPU run of the tiny flavors): an assumption, printed with the plan;
measure and pass ``--durations`` to replace it."""


@dataclass
class Duration:
    seconds: float
    """Wall seconds of one task (a per-scene stage's scene, another stage's execution)."""
    source: str
    """``file``, ``measured on <cluster>`` or ``scaled from <cluster>``."""


@dataclass
class StagePlan:
    stage: str
    shape: str
    tasks: int
    """Scenes to run (per-scene stages) or executions (others)."""
    width: int
    """Workers of one execution (a Ray Train group), else 1."""
    at_once: int
    seconds: float | None
    """Estimated wall seconds of the stage's work on the cluster (None: no duration known)."""
    gpu_hours: float | None
    source: str


def stage_durations(runs: Sequence[Mapping], cluster: str, asks_gpu: Mapping[str, bool]) -> dict[str, Duration]:
    """Per stage, the median seconds per task of finished stage runs (MLflow run dicts): those tagged with
    ``cluster`` where there are any, else the others scaled by the model (``GPU_SPEEDUP`` where the stage asks for a
    GPU on ``cluster``). A per-scene stage run's wall time covers all its scenes (``gdwm.scenes``), run by a pool of
    actors: per scene it is the wall time x min(pool, scenes) / scenes, with the pool of the run's own profile
    unknown, so taken as 1 on another cluster (conservative) and as the run's scenes here."""
    import statistics

    per: dict[tuple[str, bool], list[float]] = {}
    for r in runs:
        tags = r["tags"]
        if not (r.get("end_time") and r.get("start_time")) or "gdwm.stage" not in tags:
            continue
        wall = (r["end_time"] - r["start_time"]) / 1000
        scenes = [s for s in tags.get("gdwm.scenes", "").split(",") if s]
        here = tags.get("gdwm.cluster") == cluster
        per_task = wall / len(scenes) if scenes and not here else wall
        per.setdefault((tags["gdwm.stage"], here), []).append(per_task)
    out = {}
    for stage in {s for s, _ in per}:
        if (stage, True) in per:
            out[stage] = Duration(statistics.median(per[stage, True]), f"measured on {cluster}")
        else:
            seconds = statistics.median(per[stage, False])
            scaled = seconds / GPU_SPEEDUP if asks_gpu.get(stage) else seconds
            out[stage] = Duration(scaled, "scaled from other clusters' runs")
    return out


def plan_capacity(
    stages: Mapping[str, tuple[str, bool, int]],
    resources: Mapping[str, Mapping],
    nodes: Sequence[Node],
    durations: Mapping[str, Duration],
) -> list[StagePlan]:
    """Per stage (name -> (resource class, per scene?, tasks to run)): its shape, how many run at once on ``nodes``,
    and the estimated wall seconds and GPU-hours of its tasks."""
    out = []
    for name, (cls, per_scene, tasks) in stages.items():
        r = resources.get(cls, {})
        cpus, gpus, workers = float(r.get("num_cpus", 1)), float(r.get("num_gpus", 0)), int(r.get("num_workers", 1))
        fits = sum(n.fits(cpus, gpus) * n.count for n in nodes) if nodes else 1
        if cls == "train" and workers > 0:  # one Ray Train group per execution
            width, at_once = workers, max(1, fits // workers)
        elif cls == "train":  # in the driver, one after another
            width, at_once, gpus = 1, 1, 0.0
        else:
            pool = workers if per_scene else tasks
            width, at_once = 1, max(1, min(tasks, fits, max(pool, 1)))
        d = durations.get(name)
        seconds = gpu_hours = None
        if d is not None and tasks:
            seconds = math.ceil(tasks / at_once) * d.seconds
            gpu_hours = tasks * d.seconds * width * gpus / 3600
        elif not tasks:
            seconds, gpu_hours = 0.0, 0.0
        shape = f"{cls}: {_n(cpus)} CPU, {_n(gpus)} GPU" + (f" x {width} workers" if width > 1 else "")
        out.append(StagePlan(name, shape, tasks, width, at_once, seconds, gpu_hours, d.source if d else "unknown"))
    return out
