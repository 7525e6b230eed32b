"""The release's optional pose files and the rigid move of Gaussians into the ego frame.

The release keeps Gaussians in the frame they were reconstructed in; its loader moves ``xyz`` with
``<pose_dir>/<scene_idx>.txt``, one row-major 4x4 world->ego matrix (16 floats) per line, line =
frame index. We apply the same matrix and also rotate each Gaussian's orientation, which a
centre-only transform leaves in the old frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipelines.data.layout import DataError


def read_pose_file(path: Path, where: str) -> list[np.ndarray]:
    """All world->ego matrices of one scene, checked to be rigid (a scale change would corrupt ``scale``)."""
    if not path.is_file():
        raise DataError(f"{where}: missing pose file {path}")
    out = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            values = [float(v) for v in line.split()]
        except ValueError as e:
            raise DataError(f"{path}:{lineno}: not a row of floats ({e})") from e
        if len(values) != 16:
            raise DataError(f"{path}:{lineno}: expected 16 floats (a row-major 4x4), got {len(values)}")
        m = np.asarray(values, dtype=np.float64).reshape(4, 4)
        r = m[:3, :3]
        rigid = np.allclose(r @ r.T, np.eye(3), atol=1e-4) and np.linalg.det(r) > 0 and np.allclose(m[3], [0, 0, 0, 1])
        if not rigid:
            raise DataError(f"{path}:{lineno}: world->ego matrix is not a rigid transform")
        out.append(m)
    return out
