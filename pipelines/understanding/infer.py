"""Batched greedy answers of a world model, one Parquet row per sample (what the evaluate stage scores)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from pipelines.understanding.data import FrameStore, QASample
from pipelines.understanding.model import WorldModel

PREDICTION_SCHEMA = pa.schema(
    [
        ("sample_id", pa.string()),
        ("scene", pa.string()),
        ("frame", pa.int32()),
        ("task", pa.string()),
        ("category", pa.string()),
        ("instruction", pa.string()),
        ("answer", pa.string()),
        ("prediction", pa.string()),
    ]
)


def predict(
    model: WorldModel,
    samples: Sequence[QASample],
    store: FrameStore,
    batch_size: int,
    max_new_tokens: int,
    progress: Callable[[int, int], None] | None = None,
) -> pa.Table:
    """Greedy answers of ``samples`` in batches of ``batch_size``."""
    model.eval()
    rows = []
    for i in range(0, len(samples), batch_size):
        batch = list(samples[i : i + batch_size])
        for s, pred in zip(batch, model.answer(batch, store, max_new_tokens), strict=True):
            rows.append(
                {
                    "sample_id": s.sample_id,
                    "scene": s.scene,
                    "frame": s.frame,
                    "task": s.task,
                    "category": s.category,
                    "instruction": s.instruction,
                    "answer": s.answer,
                    "prediction": pred,
                }
            )
        if progress is not None:
            progress(min(i + batch_size, len(samples)), len(samples))
    return pa.Table.from_pylist(rows, schema=PREDICTION_SCHEMA)


def write_predictions(table: pa.Table, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(table, path)
