"""Bad data is refused before compute: the files of a dataset that differ from what ``dataset.json`` recorded (edited,
replaced or added since it was written) are read and checked before any stage runs (``data.checker``, called by
gdwm with those files): an image OpenCV cannot decode, a table that does not read, a reference box that is not a
finite, non-negative one. Each is one ``DataError`` naming the file (and the sample or row).

Only those files: a dataset as its builder wrote it was checked as it was written, and an untouched one costs
nothing here."""

from __future__ import annotations

import math
import re
from collections.abc import Iterable
from pathlib import Path

import cv2
import pyarrow.ipc as ipc
import pyarrow.parquet as pq

from pipelines.data.layout import DataError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
# Looser than the scorers' parser on purpose: a reference that says "nan" or "inf" must be found to be refused.
_NUMBER = r"[-+]?(?:nan|inf(?:inity)?|\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?"
_BOX = re.compile(rf"<box>\s*\(\s*({_NUMBER})\s*,\s*({_NUMBER})\s*\)\s*,\s*\(\s*({_NUMBER})\s*,\s*({_NUMBER})\s*\)",
                  re.IGNORECASE)  # fmt: skip
_CENTRE = re.compile(rf"cent(?:er|re)\s*:?\s*\(\s*({_NUMBER})\s*,\s*({_NUMBER})\s*,\s*({_NUMBER})\s*\)", re.IGNORECASE)


def check_files(root: str | Path, files: Iterable[str]) -> None:
    """Raise ``DataError`` for the first bad one of ``files`` (paths relative to the dataset ``root``)."""
    root = Path(root)
    for rel in sorted(files):
        path = root / rel
        suffix = path.suffix.lower()
        if suffix in IMAGE_SUFFIXES:
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if img is None or img.size == 0:
                raise DataError(f"{rel}: unreadable image (OpenCV cannot decode it)")
        elif suffix == ".parquet":
            try:
                table = pq.read_table(path)
            except Exception as e:  # pyarrow raises several kinds for a torn or foreign file
                raise DataError(f"{rel}: unreadable table ({type(e).__name__}: {e})") from None
            if rel == "qa.parquet":
                _check_references(rel, table.to_pylist())
            elif rel == "boxes2d.parquet":
                _check_rows(rel, table.to_pylist(), "box", lambda v: len(v) == 4 and min(v) >= 0)
            elif rel == "boxes3d.parquet":
                _check_rows(rel, table.to_pylist(), "size", lambda v: min(v) > 0)
                _check_rows(rel, table.to_pylist(), "center", lambda v: True)
        elif suffix == ".arrow":
            try:
                with ipc.open_file(path) as f:
                    f.schema  # noqa: B018 (reading the footer is the check)
            except Exception as e:
                raise DataError(f"{rel}: unreadable Arrow file ({type(e).__name__}: {e})") from None


def _answer(record: dict) -> str:
    turns = record.get("conversations") or []
    return next((t["value"] for t in reversed(turns) if t.get("from") in ("gpt", "assistant")), "")


def _check_references(rel: str, records: list[dict]) -> None:
    """The reference answers of grounding QA: every box finite and non-negative, every 3D centre finite (a scorer
    would otherwise skip the sample and only count it)."""
    for r in records:
        answer = _answer(r)
        for m in _BOX.finditer(answer):
            values = [float(v) for v in m.groups()]
            shown = m.group(0)[m.group(0).index("(") :]
            if not all(math.isfinite(v) for v in values):
                raise DataError(f"{rel}: sample {r.get('sample_id')}: the reference box {shown} is not finite")
            if min(values) < 0:
                raise DataError(f"{rel}: sample {r.get('sample_id')}: the reference box {shown} is negative")
        for m in _CENTRE.finditer(answer):
            if not all(math.isfinite(float(v)) for v in m.groups()):
                raise DataError(f"{rel}: sample {r.get('sample_id')}: the reference centre {m.group(0)} is not finite")


def _check_rows(rel: str, rows: list[dict], column: str, ok) -> None:
    for i, row in enumerate(rows):
        v = row.get(column)
        if v is None:
            continue
        if not all(math.isfinite(x) for x in v) or not ok(v):
            raise DataError(f"{rel}: row {i} ({row.get('scene_id')} frame {row.get('frame_idx')}): {column} {list(v)}"
                            " is not a finite, valid value")  # fmt: skip
