"""What ``gdwm data info`` prints: counts per table and task family, bytes on disk."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

from pipelines.data.layout import TASKS
from pipelines.data.reader import GSQADataset


def summarize(root: str | Path) -> dict:
    ds = GSQADataset(root)
    qa = ds.table("qa")
    by_task = Counter(qa.column("task").to_pylist())
    by_split = Counter(qa.column("split").to_pylist())
    weathers = sorted({w for ws in ds.table("scenes").column("weathers").to_pylist() for w in ws})
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
        "files": ds.meta["num_files"],
        "bytes": ds.meta["bytes"],
    }
