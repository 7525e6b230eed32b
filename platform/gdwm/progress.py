"""Stage/scene progress: a zero-CPU Ray actor collects states; the driver renders them with rich."""

from __future__ import annotations

import time
from dataclasses import dataclass

import ray
from rich.table import Table

STATUSES = ("pending", "waiting", "running", "cached", "done", "failed", "skipped", "blocked")
_STYLE = {
    "cached": "cyan",
    "done": "green",
    "failed": "red",
    "running": "yellow",
    "blocked": "magenta",
    "waiting": "blue",
}


@dataclass
class Item:
    stage: str
    scene: str | None
    status: str = "pending"
    done: int = 0
    total: int = 0
    message: str = ""
    started: float | None = None
    ended: float | None = None
    key: str = ""
    run_id: str = ""

    @property
    def wall(self) -> float | None:
        if self.started is None:
            return None
        return (self.ended or time.time()) - self.started


class ProgressBoard:
    """Plain state holder; ``ProgressActor`` is its Ray actor form."""

    def __init__(self) -> None:
        self.items: dict[tuple[str, str | None], Item] = {}

    def _item(self, stage: str, scene: str | None) -> Item:
        return self.items.setdefault((stage, scene), Item(stage, scene))

    def status(self, stage: str, scene: str | None, status: str, key: str = "", run_id: str = "", message: str = ""):
        it = self._item(stage, scene)
        it.status = status
        it.key = key or it.key
        it.run_id = run_id or it.run_id
        it.message = message or it.message
        now = time.time()
        if status == "running" and it.started is None:
            it.started = now
        if status in ("done", "failed", "cached", "skipped", "blocked"):
            it.started = it.started or now
            it.ended = now

    def update(self, stage: str, scene: str | None, done: int, total: int, message: str = ""):
        it = self._item(stage, scene)
        it.done, it.total = done, total
        it.message = message or it.message

    def snapshot(self) -> list[Item]:
        return list(self.items.values())


ProgressActor = ray.remote(num_cpus=0)(ProgressBoard)


def render(items: list[Item], order: list[str]) -> Table:
    """Per stage: status counts of its scenes, progress, wall time, key prefix, MLflow run."""
    t = Table(header_style="bold", expand=False)
    for col in ("stage", "status", "scenes", "progress", "wall s", "key", "run"):
        t.add_column(col)
    by_stage: dict[str, list[Item]] = {}
    for it in items:
        by_stage.setdefault(it.stage, []).append(it)
    for stage in order:
        its = by_stage.get(stage, [])
        head = next((i for i in its if i.scene is None), None)
        scenes = [i for i in its if i.scene is not None]
        status = head.status if head else "pending"
        style = _STYLE.get(status, "")
        counts = ""
        if scenes:
            c = {s: sum(1 for i in scenes if i.status == s) for s in STATUSES}
            counts = " ".join(f"{s} {n}" for s, n in c.items() if n)
        prog = head.message if head else ""
        if head and head.total:
            prog = f"{head.done}/{head.total} {head.message}".strip()
        wall = f"{head.wall:.1f}" if head and head.wall is not None else ""
        t.add_row(
            stage,
            f"[{style}]{status}[/{style}]" if style else status,
            counts,
            prog,
            wall,
            (head.key[:12] if head else ""),
            (head.run_id[:12] if head else ""),
        )
    return t
