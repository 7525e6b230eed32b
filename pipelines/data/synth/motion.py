"""Closed-form motion of an agent in the road frame: speed ramps, lane changes, crossings.

Every agent (the ego included) follows ``Motion``: along the road, constant acceleration until
a target speed, then constant speed; across it, a constant drift plus an optional cosine lane
change. Closed forms keep every frame exact and the velocities analytic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipelines.data.synth.road import Road


@dataclass(frozen=True)
class State:
    """World state at the sampled times (T of them)."""

    xy_T2: np.ndarray
    yaw_T: np.ndarray
    velocity_T2: np.ndarray
    s_T: np.ndarray
    lat_T: np.ndarray

    @property
    def speed_T(self) -> np.ndarray:
        return np.linalg.norm(self.velocity_T2, axis=-1)


@dataclass(frozen=True)
class Motion:
    s0: float
    """Arc length at t = 0."""
    lat0: float
    """Lateral offset at t = 0 (+ = left of the centreline)."""
    v0: float = 0.0
    """Speed along +s at t = 0 (negative = driving against +s)."""
    accel: float = 0.0
    """Along-road acceleration, applied until the speed reaches ``v_end``."""
    v_end: float = 0.0
    """Speed at which the acceleration stops (ignored when ``accel`` is 0)."""
    vlat: float = 0.0
    """Constant lateral speed (crossing pedestrians)."""
    lc_offset: float = 0.0
    """Lateral displacement of a lane change (0 = none)."""
    lc_start: float = 0.0
    """Time the lane change starts, seconds."""
    lc_duration: float = 1.0
    """Duration of the lane change, seconds."""
    facing: float = 0.0
    """Yaw relative to the road when standing still: 0 = along +s, pi = against it."""

    def along(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(s, ds/dt) at times ``t``."""
        t = np.asarray(t, dtype=np.float64)
        if self.accel == 0.0:
            return self.s0 + self.v0 * t, np.full_like(t, self.v0)
        t_c = max((self.v_end - self.v0) / self.accel, 0.0)
        tt = np.minimum(t, t_c)
        s = self.s0 + self.v0 * tt + 0.5 * self.accel * tt**2 + self.v_end * (t - tt)
        ds = np.where(t < t_c, self.v0 + self.accel * tt, self.v_end)
        return s, ds

    def across(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(lat, dlat/dt) at times ``t``."""
        t = np.asarray(t, dtype=np.float64)
        lat = self.lat0 + self.vlat * t
        dlat = np.full_like(t, self.vlat)
        if self.lc_offset != 0.0:
            u = np.clip((t - self.lc_start) / self.lc_duration, 0.0, 1.0)
            lat = lat + self.lc_offset * 0.5 * (1.0 - np.cos(np.pi * u))
            inside = (u > 0.0) & (u < 1.0)
            dlat = dlat + np.where(inside, self.lc_offset * np.pi / (2 * self.lc_duration) * np.sin(np.pi * u), 0.0)
        return lat, dlat

    def state(self, road: Road, t: np.ndarray) -> State:
        s, ds = self.along(t)
        lat, dlat = self.across(t)
        vel = road.velocity(s, lat, ds, dlat)
        moving = np.hypot(ds, dlat) > 1e-6
        # Moving agents face their velocity; standing ones keep their facing.
        rel = np.where(moving, np.arctan2(dlat, ds * (1.0 - road.curvature * lat)), self.facing)
        return State(road.to_world(s, lat), road.heading(s) + rel, vel, s, lat)
