"""Training and evaluation examples of the generation branch (Sec. Instruction-controllable 4D Scene Generation).

A target is a camera state relative to frame ``f``: a lateral shift (ground truth re-rendered by the synthetic
generator), a future frame ``f + h`` (ground truth recorded), or a weather variant of the same view (instruction
editing; synthetic_mini's weather renders are the pairs). Every example carries the reference view (frame ``f``,
clear), the low-level conditions (frame ``f``'s Gaussians projected into the target camera) and the ground truth;
its prompt (``GenTarget.qa``) asks for the camera state and carries any editing intent, so C_L carries it too.

Legend: ``H x W`` the model's image size.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import torch

from pipelines.data.layout import DataError
from pipelines.data.reader import GSQADataset, gaussians_from_table, read_arrow
from pipelines.data.synth.novel_view import render_view
from pipelines.generation.conditions import (
    future_camera_pose,
    horizon_frames,
    low_level_conditions,
    shifted_camera_pose,
    target_name,
)
from pipelines.generation.edits import Edit, ReferenceFrame, Weather, apply_edit, edit_instruction
from pipelines.understanding.data import QASample

KINDS = ("shift", "future", "weather")


@dataclass(frozen=True)
class GenTarget:
    scene: str
    frame: int
    camera: str
    kind: str
    """``shift``, ``future`` or ``weather``."""
    lateral_m: float = 0.0
    """Shift targets: metres to the left (+) or right (-) in the ego frame."""
    horizon_frames: int = 0
    """Future targets: frames ahead."""
    horizon_s: float = 0.0
    weather: str = "clear"
    """Weather targets: the variant to generate."""
    ego_pose: tuple[float, ...] | None = None
    """Future targets on a predicted trajectory: the predicted ego pose at the horizon in frame ``frame``'s ego
    frame (4x4, row-major); None = the recorded pose."""
    edit: str = ""
    """The editing intent, as instruction text (``edits.edit_instruction``), that the prompt of C_L carries; empty =
    none. A weather target without one carries its weather's (``Change the weather to rain.``)."""

    @property
    def name(self) -> str:
        """Metric name of the target family: ``shift_1m``, ``shift_-1m``, ``future_2s``, ``weather_rain``."""
        if self.kind == "shift":
            return target_name(lateral_m=self.lateral_m)
        if self.kind == "future" and self.ego_pose is not None:
            return target_name(future_s=self.horizon_s).replace("future_", "future_pred_")
        if self.kind == "future":
            return target_name(future_s=self.horizon_s)
        return f"weather_{self.weather}"

    @property
    def edit_text(self) -> str:
        """The editing instruction of the prompt: ``edit``, or a weather target's own weather edit."""
        if self.edit or self.kind != "weather":
            return self.edit
        return edit_instruction(Weather(self.weather))

    @property
    def instruction(self) -> str:
        """The view request (camera state), then the editing intent if any: the text the LLM turns into C_L."""
        if self.kind == "shift" and self.lateral_m:
            side = "left" if self.lateral_m > 0 else "right"
            view = f"generate the {self.camera} view shifted {abs(self.lateral_m):g} m to the {side}."
        elif self.kind == "future":
            view = f"generate the {self.camera} view {self.horizon_s:g} s ahead."
        else:
            view = f"generate the {self.camera} view."
        return " ".join(filter(None, [f"Based on <gauss>, {view}", self.edit_text]))

    def qa(self) -> QASample:
        """The prompt the LLM turns into C_L."""
        sid = f"{self.scene}/{self.frame:05d}/gen/{self.camera}/{self.name}" + ("/edit" if self.edit else "")
        return QASample(sid, self.scene, self.frame, "gen", self.instruction, "", (self.camera,))


def enumerate_targets(
    ds: GSQADataset,
    scenes: list[str],
    cameras: list[str],
    shifts_m: list[float],
    horizons_s: list[float],
    weathers: list[str],
) -> list[GenTarget]:
    """Every (scene, frame, camera) with each shift, each horizon that stays inside the scene, each weather."""
    out = []
    for sid in scenes:
        scene = ds.scene(sid)
        rate = float(scene.info["frame_rate_hz"])
        for f in range(scene.num_frames):
            for cam in cameras:
                out += [GenTarget(sid, f, cam, "shift", lateral_m=float(m)) for m in shifts_m]
                for s in horizons_s:
                    h = horizon_frames(s, rate)
                    if f + h < scene.num_frames:
                        out.append(GenTarget(sid, f, cam, "future", horizon_frames=h, horizon_s=float(s)))
                out += [GenTarget(sid, f, cam, "weather", weather=w) for w in weathers if w in scene.weathers]
    return out


@dataclass
class GenExample:
    target: GenTarget
    target_rgb: torch.Tensor
    """[3, H, W] in [0, 1]."""
    target_depth: torch.Tensor
    """[H, W] metres, 0 = none."""
    ref_rgb: torch.Tensor
    ref_depth: torch.Tensor
    cond_rgb: torch.Tensor
    cond_depth: torch.Tensor
    cond_mask: torch.Tensor
    """[H, W] float 0/1."""


def frame_gaussians(rec_dir: Path, scene: str, frame: int) -> dict[str, np.ndarray]:
    path = rec_dir / "gaussians" / f"{frame:05d}.arrow"
    return gaussians_from_table(read_arrow(path, f"{scene}/frame_{frame:03d} reconstructed gaussians"))


def _rgb(img_HW3: np.ndarray, hw: tuple[int, int]) -> torch.Tensor:
    small = cv2.resize(img_HW3, (hw[1], hw[0]), interpolation=cv2.INTER_AREA)
    return torch.from_numpy(np.ascontiguousarray(small)).permute(2, 0, 1).float() / 255.0


def _nearest(a_HW: np.ndarray, hw: tuple[int, int]) -> torch.Tensor:
    return torch.from_numpy(cv2.resize(a_HW.astype(np.float32), (hw[1], hw[0]), interpolation=cv2.INTER_NEAREST))


def target_pose(ds: GSQADataset, t: GenTarget) -> np.ndarray:
    """The target camera's sensor->ego pose in frame ``t.frame``'s ego frame."""
    scene = ds.scene(t.scene)
    base = scene.cameras[t.camera].sensor2ego_44
    if t.kind == "shift":
        return shifted_camera_pose(base, lateral_m=t.lateral_m)
    if t.kind == "future" and t.ego_pose is not None:
        return np.asarray(t.ego_pose, dtype=np.float64).reshape(4, 4) @ base
    if t.kind == "future":
        return future_camera_pose(scene.ego_poses, t.frame, t.horizon_frames, base, scene=t.scene)
    return base


def ground_truth(ds: GSQADataset, t: GenTarget, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rgb uint8, depth metres) the target camera saw (shift: re-rendered; synthetic_mini only)."""
    frame = ds.scene(t.scene).frame(t.frame)
    if t.kind == "shift":
        return render_view(ds.root, t.scene, t.frame, t.camera, pose)
    if t.kind == "future":
        later = ds.scene(t.scene).frame(t.frame + t.horizon_frames)
        return later.image(t.camera), later.depth(t.camera)
    return frame.image(t.camera, t.weather), frame.depth(t.camera)


def build_example(
    ds: GSQADataset, t: GenTarget, gaussians: dict[str, np.ndarray], hw: tuple[int, int], edited: bool = False
) -> GenExample:
    """One example at the model's size ``hw``. ``edited``: the Gaussians were edited, so there is no ground truth
    (the reference view stands in as the target)."""
    scene = ds.scene(t.scene)
    cam = scene.cameras[t.camera]
    pose = target_pose(ds, t)
    cond = low_level_conditions(gaussians, cam.K_33, pose, cam.width, cam.height, scene=t.scene, frame=t.frame)
    frame = scene.frame(t.frame)
    ref_rgb, ref_depth = frame.image(t.camera), frame.depth(t.camera)
    gt_rgb, gt_depth = (ref_rgb, ref_depth) if edited else ground_truth(ds, t, pose)
    if gt_rgb.shape[:2] != (cam.height, cam.width):
        raise DataError(
            f"{t.scene}/frame_{t.frame:03d} {t.camera}: ground truth is {gt_rgb.shape[:2]}, expected "
            f"{(cam.height, cam.width)}"
        )
    cond_rgb = (np.clip(np.asarray(cond.rgb), 0, 1) * 255).astype(np.uint8)
    return GenExample(
        t,
        _rgb(gt_rgb, hw),
        _nearest(gt_depth, hw),
        _rgb(ref_rgb, hw),
        _nearest(ref_depth, hw),
        _rgb(cond_rgb, hw),
        _nearest(np.asarray(cond.depth), hw),
        _nearest(np.asarray(cond.mask, dtype=np.float32), hw),
    )


def edited_example(
    ds: GSQADataset,
    t: GenTarget,
    edit: Edit,
    gaussians: dict[str, np.ndarray],
    boxes: list[dict],
    hw: tuple[int, int],
    *,
    t_s: float = 0.0,
    reference: ReferenceFrame | None = None,
) -> tuple[GenExample, QASample]:
    """One view of ``edit`` conditioned as the paper means it (Eq. v_hat: editing intent is part of C_L).

    Low-level: C_I, C_D projected from the edited Gaussians (``apply_edit``; a weather edit leaves them as they
    are). High-level: the prompt of C_L carries the instruction text (``edit_instruction``) for every edit kind. A
    weather edit asks for that weather's target, whose prompt is the one the weather targets were trained with; any
    other edit keeps ``t``'s camera state. There is no ground truth: the reference view stands in as the target.
    """
    g = apply_edit(edit, gaussians, boxes, scene=t.scene, frame=t.frame, t_s=t_s, reference=reference)
    if isinstance(edit, Weather):
        t = replace(t, kind="weather", weather=edit.name, lateral_m=0.0, horizon_frames=0, horizon_s=0.0, ego_pose=None)
    target = replace(t, edit=edit_instruction(edit))
    return build_example(ds, target, g, hw, edited=True), target.qa()


def stack(examples: list[GenExample]) -> dict[str, torch.Tensor]:
    keys = ("target_rgb", "target_depth", "ref_rgb", "ref_depth", "cond_rgb", "cond_depth", "cond_mask")
    return {k: torch.stack([getattr(e, k) for e in examples]) for k in keys}
