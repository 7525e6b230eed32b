"""Planning decisions and trajectory targets derived from ego poses and 3D boxes.

Planning (``plan``) rules, for frame t and a horizon of H frames (``plan_horizon_s`` x rate),
using the stored ego->world poses E:

- speeds: v_now = |xy(t+1) - xy(t)| * rate, v_end = |xy(t+H) - xy(t+H-1)| * rate;
  ``stop`` if v_end < 0.3 m/s; else ``decelerate`` if v_end - v_now <= -1.0;
  ``accelerate`` if v_end - v_now >= +1.0; ``keep speed`` if |v_end - v_now| <= 0.5;
  anything else (and v_end in [0.3, 0.6)) is ambiguous and gets no question.
- direction: with inv(E[t]) @ E[t+H] = (x_H, y_H, yaw change dpsi):
  ``go straight`` if |dpsi| < 3 deg and |y_H| < 0.75 m;
  ``turn left``/``turn right`` if |dpsi| >= 6 deg and the chord angle atan2(y_H, x_H) is within
  2 deg of dpsi / 2 (a constant-curvature arc);
  ``change lane left``/``right`` if |y_H| >= 2.5 m and |dpsi| < 4 deg;
  anything else is ambiguous. The generator also requires the scene's own truth (road bend,
  lane-change window) to agree, so the start of a lane change is never called a turn.
- the obstacle a reason names: the nearest 3D box with centre x > 0, |y| < 1.75 m (the ego
  lane corridor) and ego-xy distance <= 40 m.

Trajectory (``traj``, the paper's format): a 10-frame window [k, k+9]; all poses are expressed
in the ego frame of its 5th frame (k+4). The question lists frames k..k+3 (the "last 4 frames",
negative x when driving forward); the answer lists frames k+4..k+9 -- the 5th frame, the identity
pose [0, 0, 0, 0, 0, 0, 1], first, then the next 5 -- exactly as the paper's example shows. Each
pose is [x, y, z, qx, qy, qz, qw] (qw >= 0) with 2 decimals.
"""

from __future__ import annotations

import numpy as np

from pipelines.data.layout import matrix_to_quat_wxyz

SPEED_DECISIONS = ("stop", "decelerate", "accelerate", "keep speed")
DIRECTION_DECISIONS = ("turn left", "turn right", "change lane left", "change lane right", "go straight")
STOP_BELOW = 0.3
STOP_AMBIGUOUS_BELOW = 0.6
SPEED_CHANGE = 1.0
KEEP_WITHIN = 0.5
TURN_DEG = 6.0
STRAIGHT_DEG = 3.0
STRAIGHT_OFFSET_M = 0.75
ARC_TOL_DEG = 2.0
LANE_CHANGE_OFFSET_M = 2.5
LANE_CHANGE_MAX_DEG = 4.0
LANE_HALF_WIDTH = 1.75
OBSTACLE_RANGE_M = 40.0
HISTORY = 4
FUTURE = 6
WINDOW = HISTORY + FUTURE


def speed_decision(ego2world_F44: np.ndarray, t: int, horizon: int, rate_hz: float) -> tuple[str | None, dict]:
    xy = ego2world_F44[:, :2, 3]
    v_now = float(np.linalg.norm(xy[t + 1] - xy[t]) * rate_hz)
    v_end = float(np.linalg.norm(xy[t + horizon] - xy[t + horizon - 1]) * rate_hz)
    facts = {"v_now": v_now, "v_end": v_end}
    dv = v_end - v_now
    if v_end < STOP_BELOW:
        return "stop", facts
    if v_end < STOP_AMBIGUOUS_BELOW:
        return None, facts
    if dv <= -SPEED_CHANGE:
        return "decelerate", facts
    if dv >= SPEED_CHANGE:
        return "accelerate", facts
    if abs(dv) <= KEEP_WITHIN:
        return "keep speed", facts
    return None, facts


def relative_motion(ego2world_F44: np.ndarray, t: int, horizon: int) -> tuple[float, float, float]:
    """(x_H, y_H, dpsi in degrees) of frame t+H in the ego frame of frame t."""
    rel = np.linalg.inv(ego2world_F44[t]) @ ego2world_F44[t + horizon]
    return float(rel[0, 3]), float(rel[1, 3]), float(np.degrees(np.arctan2(rel[1, 0], rel[0, 0])))


def direction_decision(ego2world_F44: np.ndarray, t: int, horizon: int) -> tuple[str | None, dict]:
    x, y, dpsi = relative_motion(ego2world_F44, t, horizon)
    facts = {"end_offset_m": [x, y], "yaw_change_deg": dpsi}
    if abs(dpsi) < STRAIGHT_DEG and abs(y) < STRAIGHT_OFFSET_M:
        return "go straight", facts
    chord = np.degrees(np.arctan2(y, x))
    if abs(dpsi) >= TURN_DEG and abs(chord - dpsi / 2) <= ARC_TOL_DEG:
        return ("turn left" if dpsi > 0 else "turn right"), facts
    if abs(y) >= LANE_CHANGE_OFFSET_M and abs(dpsi) < LANE_CHANGE_MAX_DEG:
        return ("change lane left" if y > 0 else "change lane right"), facts
    return None, facts


def lane_obstacle(boxes3d: list[dict]) -> dict | None:
    """The nearest box ahead in the ego lane corridor within range, or None."""
    best, best_d = None, OBSTACLE_RANGE_M
    for row in boxes3d:
        cx, cy = row["center"][0], row["center"][1]
        d = float(np.hypot(cx, cy))
        if cx > 0 and abs(cy) < LANE_HALF_WIDTH and d <= best_d:
            best, best_d = row, d
    return best


def _fmt(v: float) -> str:
    return f"{round(float(v), 2) + 0.0:.2f}"  # + 0.0 turns -0.0 into 0.0


def pose_vector(rel_44: np.ndarray) -> list[float]:
    """[x, y, z, qx, qy, qz, qw] of a relative pose (quaternion with qw >= 0)."""
    w, x, y, z = matrix_to_quat_wxyz(rel_44[:3, :3])
    return [float(v) for v in (*rel_44[:3, 3], x, y, z, w)]


def format_poses(poses: list[list[float]]) -> str:
    return "[PT, " + ", ".join("[" + ", ".join(_fmt(v) for v in p) + "]" for p in poses) + "]"


def trajectory_window(ego2world_F44: np.ndarray, start: int) -> tuple[list[list[float]], list[list[float]]]:
    """(4 history poses, 6 future poses) of the window starting at ``start``, in frame start+4's ego frame."""
    ref_inv = np.linalg.inv(ego2world_F44[start + HISTORY])
    poses = [pose_vector(ref_inv @ ego2world_F44[start + i]) for i in range(WINDOW)]
    return poses[:HISTORY], poses[HISTORY:]
