"""``data.checker``: the files of a dataset that differ from their record are read before any stage runs."""

from __future__ import annotations

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from pipelines.data.check import check_files
from pipelines.data.layout import BOXES2D_SCHEMA, BOXES3D_SCHEMA, DataError


def _row2d(box):
    return {"scene_id": "s0", "frame_idx": 3, "camera": "CAM_FRONT", "instance_id": "a", "box": box,
            "visible_fraction": 1.0}  # fmt: skip


def _row3d(size):
    return {"scene_id": "s0", "frame_idx": 1, "instance_id": "a", "category": "car", "attribute": "",
            "center": [1, 2, 0], "size": size, "yaw": 0.0, "velocity": [0, 0]}  # fmt: skip


@pytest.mark.parametrize(
    "name, schema, rows, message",
    [
        ("boxes2d.parquet", BOXES2D_SCHEMA, [_row2d([1, 2, 3, 4]), _row2d([1, float("nan"), 3, 4])],
         "boxes2d.parquet: row 1 (s0 frame 3): box [1.0, nan, 3.0, 4.0] is not a finite, valid value"),
        ("boxes3d.parquet", BOXES3D_SCHEMA, [_row3d([4, 2, 0])],
         "boxes3d.parquet: row 0 (s0 frame 1): size [4.0, 2.0, 0.0] is not a finite, valid value"),
    ],
)  # fmt: skip
def test_tables_with_boxes_that_are_not_finite_or_valid_are_refused(tmp_path, name, schema, rows, message):
    pq.write_table(pa.Table.from_pylist(rows, schema=schema), tmp_path / name)
    with pytest.raises(DataError) as e:
        check_files(tmp_path, [name])
    assert str(e.value) == message


def test_a_torn_table_and_untouched_files_elsewhere(tmp_path):
    (tmp_path / "frames.parquet").write_bytes(b"PAR1 not a table")
    with pytest.raises(DataError, match=r"^frames\.parquet: unreadable table \("):
        check_files(tmp_path, ["frames.parquet"])
    check_files(tmp_path, [])  # only the files it is given are read
