"""Material ids, named colours and LiDAR reflectivities shared by the scene, renderer and LiDAR."""

from __future__ import annotations

from enum import IntEnum

import numpy as np


class Material(IntEnum):
    GROUND = 0
    BUILDING = 1
    PAINT = 2
    """Vehicle body: paint, wheels drawn on the sides."""
    CABIN = 3
    """Car cabin / truck cab: glass on the sides, paint on top."""
    BUS = 4
    """Bus body: paint with a window band."""
    CARGO = 5
    TRUNK = 6
    FOLIAGE = 7
    CLOTH = 8
    SKIN = 9
    POLE = 10
    LAMP = 11


# Named colours; the names are what QA answers say ("the red car").
VEHICLE_COLOURS = {
    "white": (0.90, 0.90, 0.88),
    "black": (0.07, 0.07, 0.08),
    "silver": (0.66, 0.68, 0.71),
    "red": (0.72, 0.08, 0.08),
    "blue": (0.10, 0.22, 0.66),
    "green": (0.12, 0.45, 0.18),
    "yellow": (0.90, 0.76, 0.10),
    "orange": (0.90, 0.42, 0.08),
}
BUS_COLOURS = ("white", "yellow", "red", "blue")
TRUCK_COLOURS = ("white", "silver", "blue", "red", "orange")
CLOTHING_COLOURS = {
    "red": (0.70, 0.10, 0.12),
    "blue": (0.12, 0.25, 0.62),
    "green": (0.15, 0.48, 0.20),
    "yellow": (0.88, 0.78, 0.15),
    "white": (0.88, 0.88, 0.86),
    "black": (0.08, 0.08, 0.09),
}
FACADE_COLOURS = (
    (0.78, 0.70, 0.58),
    (0.64, 0.40, 0.30),
    (0.72, 0.72, 0.70),
    (0.55, 0.58, 0.62),
    (0.85, 0.80, 0.68),
    (0.48, 0.36, 0.30),
)
SKIN = (0.80, 0.62, 0.48)
TRUNK = (0.36, 0.25, 0.15)
FOLIAGE = (0.20, 0.42, 0.14)
POLE = (0.45, 0.46, 0.48)
LAMP = (0.95, 0.92, 0.75)

# Diffuse reflectivity in [0, 1] per material as LiDAR sees it (times 255 = nuScenes intensity scale).
REFLECTIVITY = np.array([0.10, 0.30, 0.45, 0.25, 0.40, 0.35, 0.20, 0.18, 0.15, 0.20, 0.55, 0.80], dtype=np.float32)
