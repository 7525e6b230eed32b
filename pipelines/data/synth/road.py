"""The road: a straight or constant-curvature centreline and the road frame (s, l) around it.

World frame: flat ground z = 0, the centreline starts at the origin heading +x. Road frame:
``s`` arc length along the centreline, ``l`` signed lateral offset (+ = left). Traffic keeps
right, so the ego direction (+s) uses the lanes with l < 0.

Cross-section (|l|, metres): two 3.5 m lanes per direction up to 7.0, a parking strip to 9.5,
a kerb to 9.7, the sidewalk to 12.5, then a grass verge; buildings start at 14.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

LANE_WIDTH = 3.5
LANES_PER_DIRECTION = 2
CARRIAGEWAY_HALF = LANE_WIDTH * LANES_PER_DIRECTION
PARKING_OUTER = 9.5
KERB_OUTER = 9.7
SIDEWALK_OUTER = 12.5
BUILDING_SETBACK = 14.0
PARKING_L = 8.25
"""Lateral offset of parked cars' centres (middle of the parking strip)."""
EGO_LANES = (-0.5 * LANE_WIDTH, -1.5 * LANE_WIDTH)
"""Centre offsets of the ego-direction lanes: inner (next to the centre line), outer."""
ONCOMING_LANES = (0.5 * LANE_WIDTH, 1.5 * LANE_WIDTH)


@dataclass(frozen=True)
class Road:
    curvature: float = 0.0
    """1/m, + = bends left; 0 = straight."""
    crosswalks: tuple[float, ...] = ()
    """Arc lengths where a 4 m zebra crossing starts."""

    def heading(self, s: np.ndarray) -> np.ndarray:
        return self.curvature * np.asarray(s, dtype=np.float64)

    def to_world(self, s: np.ndarray, lat: np.ndarray) -> np.ndarray:
        """[..., 2] world xy of road-frame points."""
        s = np.asarray(s, dtype=np.float64)
        lat = np.asarray(lat, dtype=np.float64)
        k = self.curvature
        if k == 0.0:
            return np.stack(np.broadcast_arrays(s, lat), axis=-1)
        th = k * s
        r = 1.0 / k
        # Centre of the circle at (0, r); a point (s, l) lies at radius (r - lat) from it.
        return np.stack([(r - lat) * np.sin(th), r - (r - lat) * np.cos(th)], axis=-1)

    def to_road(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Road-frame (s, l) of world xy (valid within half a turn of the start, which scenes stay in)."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        k = self.curvature
        if k == 0.0:
            return x, y
        r = 1.0 / k
        vx, vy = x, y - r
        dist = np.hypot(vx, vy)
        if r > 0:
            return np.arctan2(vx, -vy) * r, r - dist
        return np.arctan2(-vx, vy) * r, r + dist

    def velocity(self, s: np.ndarray, lat: np.ndarray, ds: np.ndarray, dl: np.ndarray) -> np.ndarray:
        """[..., 2] world velocity of a point moving with (ds/dt, dl/dt) in the road frame."""
        th = self.heading(s)
        tangent = np.stack([np.cos(th), np.sin(th)], axis=-1)
        normal = np.stack([-np.sin(th), np.cos(th)], axis=-1)
        along = np.asarray(ds) * (1.0 - self.curvature * np.asarray(lat))
        return along[..., None] * tangent + np.asarray(dl)[..., None] * normal
