"""What ``gdwm data info`` prints: counts per table and task family, generation samples, bytes on disk."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

from rich.console import RenderableType
from rich.table import Table

from pipelines.data.layout import TASKS
from pipelines.data.reader import GSQADataset


def render(root: str | Path) -> list[RenderableType]:
    """The summary of the dataset at ``root`` as lines and tables for gdwm to print (the data options'
    ``summarizer``)."""
    return renderables(summarize(root))


def summarize(root: str | Path) -> dict:
    ds = GSQADataset(root)
    qa = ds.table("qa")
    by_task = Counter(qa.column("task").to_pylist())
    by_split = Counter(qa.column("split").to_pylist())
    weathers = sorted({w for ws in ds.table("scenes").column("weathers").to_pylist() for w in ws})
    world = ds.table("world")  # optional: empty where the dataset has no generation samples
    world_by_split = Counter(world.column("split").to_pylist())
    return {
        "name": ds.meta["name"],
        "root": str(ds.root.resolve()),
        "source": ds.meta["source"],
        "fingerprint": ds.fingerprint,
        "scenes": ds.meta["num_scenes"],
        "frames": ds.meta["num_frames"],
        "cameras": ds.cameras,
        "weathers": weathers,
        "boxes3d": ds.table("boxes3d").num_rows,
        "boxes2d": ds.table("boxes2d").num_rows,
        "qa_total": qa.num_rows,
        "qa_per_task": {t: by_task.get(t, 0) for t in (*TASKS, *sorted(set(by_task) - set(TASKS)))},
        "qa_per_split": dict(sorted(by_split.items())),
        "world_samples": world.num_rows,
        "world_per_split": dict(sorted(world_by_split.items())),
        "clip_text_features": (clip := ds.table("clip_text").num_rows),
        "notes": _notes(world.num_rows, world_by_split, clip),
        "files": ds.meta["num_files"],
        "bytes": ds.meta["bytes"],
    }


def _notes(world: int, world_by_split: Counter, clip: int) -> list[str]:
    """Lines ``gdwm data info`` prints under the tables: the optional generation samples and CLIP text features."""
    notes = []
    if world:
        notes.append(f"world samples: {world} ({', '.join(f'{k} {v}' for k, v in sorted(world_by_split.items()))})")
    if clip:
        notes.append(f"CLIP text features: {clip} QA samples")
    return notes


def _fmt_bytes(n: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{n} B"
        n /= 1024
    return f"{n} B"


def renderables(s: dict) -> list[RenderableType]:
    """``summarize``'s dict as tables: counts, bytes on disk, QA per task family and split."""
    out: list[RenderableType] = [
        f"[bold]{s['name']}[/bold] at {s['root']}  (source {s['source']}, fingerprint {s['fingerprint'][:12]})"
    ]
    t = Table(show_header=True, header_style="bold")
    for col in ("scenes", "frames", "cameras", "weathers", "3D boxes", "2D boxes", "QA", "files", "on disk"):
        t.add_column(col, justify="right")
    t.add_row(
        str(s["scenes"]),
        str(s["frames"]),
        str(len(s["cameras"])),
        ",".join(s["weathers"]) or "-",
        str(s["boxes3d"]),
        str(s["boxes2d"]),
        str(s["qa_total"]),
        str(s["files"]),
        _fmt_bytes(s["bytes"]),
    )
    out.append(t)
    q = Table(title="QA per task family", show_header=True, header_style="bold")
    for task in s["qa_per_task"]:
        q.add_column(task, justify="right")
    q.add_row(*(str(v) for v in s["qa_per_task"].values()))
    out.append(q)
    splits = ", ".join(f"{k} {v}" for k, v in s["qa_per_split"].items())
    out.append(f"QA splits: {splits or '-'}")
    out += s.get("notes", ())  # what the tables do not show, one line each
    return out
