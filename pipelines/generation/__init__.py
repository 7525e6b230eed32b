"""Instruction-controllable 4D scene generation (paper: Sec. Instruction-controllable 4D Scene Generation): target
cameras, the low-level conditions C_I / C_D projected from the Gaussians, and the 4D edits applied before."""

from pipelines.generation.conditions import (
    SPATIAL_SHIFTS,
    TEMPORAL_HORIZONS_S,
    Conditions,
    Target,
    default_targets,
    future_camera_pose,
    horizon_frames,
    low_level_conditions,
    shifted_camera_pose,
    target_name,
)
from pipelines.generation.edits import (
    Edit,
    InsertVehicle,
    MoveVehicle,
    ReferenceFrame,
    RemoveVehicle,
    StopVehicle,
    Weather,
    apply_edit,
    edit_instruction,
    parse_edit,
)

__all__ = [
    "SPATIAL_SHIFTS",
    "TEMPORAL_HORIZONS_S",
    "Conditions",
    "Edit",
    "InsertVehicle",
    "MoveVehicle",
    "ReferenceFrame",
    "RemoveVehicle",
    "StopVehicle",
    "Target",
    "Weather",
    "apply_edit",
    "default_targets",
    "edit_instruction",
    "future_camera_pose",
    "horizon_frames",
    "low_level_conditions",
    "parse_edit",
    "shifted_camera_pose",
    "target_name",
]
