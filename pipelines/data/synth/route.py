"""The planned route of a synthetic scene's ego: what navigation knows before the ego drives, from the map alone.

The route is the centreline of the lane the ego starts in, along the road (straight or bending), over a fixed
stretch of the map: from 30 m behind the ego's start to further ahead than any ego of the clip can drive. It is a
function of the road and the starting lane only, never of the ego's speed profile or manoeuvres (a lane change, a
stop), so it cannot tell the planning or trajectory answers. ``build`` records it per scene in the dataset's
``routes.json``; the driving-aware selector's ``path=route`` reads it there (``model_zoo.selectors.route_path``).
"""

from __future__ import annotations

import numpy as np

from pipelines.data.synth.scene import Scene

BEHIND_M = 30.0
"""Route behind the ego's start."""
MAX_SPEED_MPS = 15.0
"""Faster than any ego scenario drives, so the route outruns the clip."""
MARGIN_M = 60.0
"""Route beyond the farthest point such an ego could reach by the end of the clip."""
STEP_M = 1.0
"""Spacing of the route's points along the road."""


def planned_route(scene: Scene) -> np.ndarray:
    """``[P, 2]`` world xy of the route, in driving order, ``STEP_M`` apart."""
    s0 = scene.ego.s0
    ahead = MAX_SPEED_MPS * float(scene.times[-1]) + MARGIN_M
    s = np.arange(s0 - BEHIND_M, s0 + ahead + 1e-9, STEP_M)
    return scene.road.to_world(s, np.full_like(s, scene.ego.lat0))
