"""``gdwm generate`` and ``gdwm edit``: views from the trained generation branch, as PNGs, an MP4 and an MLflow run.

Both first run the pipeline up to ``diffusion`` (all cache hits once trained), then load the diffusion model, the
LoRA'd world model (C_L) and the scene's reconstructed Gaussians (low-level conditions). Outputs go under
``<workdir>/generated/`` and ``<workdir>/edits/``.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

from annotated_types import Ge, Gt, Interval

from gdwm.api import SEED


@dataclass
class GenerateArgs:
    """``gdwm generate args.scene=... args.frame=... args.shifts_m=[1,-1] args.horizons_s=[1]``."""

    scene: str | None = None
    """Scene id (required)."""
    frame: Annotated[int, Ge(0)] = 0
    """Frame the conditions come from."""
    camera: str = "CAM_FRONT"
    """Camera whose view is shifted or carried forward."""
    shifts_m: Annotated[list[float], Interval(ge=-100, le=100)] = field(default_factory=lambda: [-1.0, 1.0])
    """Lateral shifts, metres (+ = left); one view each, in this order in the MP4."""
    horizons_s: Annotated[list[float], Gt(0)] = field(default_factory=list)
    """Future horizons, seconds."""
    seed: Annotated[int, SEED] = 0
    """Sampling seed (same seed, same output)."""
    fps: Annotated[float, Gt(0)] = 2.0
    """Frame rate of the MP4."""


@dataclass
class EditArgs:
    """``gdwm edit args.scene=... args.frame=... args.edit="Remove vehicle scene-0003-car-01 from the scene."``."""

    scene: str | None = None
    """Scene id (required)."""
    frame: Annotated[int, Ge(0)] = 0
    """First frame of the edited clip."""
    frames: Annotated[int, Ge(1)] = 4
    """Frames in the clip (geometry edits apply to every frame's Gaussians, so the clip stays consistent)."""
    camera: str = "CAM_FRONT"
    """Camera of the clip."""
    edit: str | None = None
    """The edit: instruction text or JSON (``pipelines.generation.edits.parse_edit``), e.g. "Change the weather to
    rain." (required)."""
    seed: Annotated[int, SEED] = 0
    """Sampling seed; the unedited clip (original Gaussians, no instruction in C_L) uses the same seed, so
    differences come from the edit, carried by the edited Gaussians and by the instruction in C_L."""
    fps: Annotated[float, Gt(0)] = 2.0
    """Frame rate of the MP4."""


def _require(value: Any, key: str) -> Any:
    if value in (None, ""):
        from gdwm.api import CommandError

        raise CommandError(f"{key} is required")
    return value


@dataclass
class Runtime:
    ds: Any
    model: Any
    world: Any
    rec_dirs: dict[str, Path]
    distill_dirs: dict[str, Path]
    diffusion_key: str


def _runtime(cfg) -> Runtime:
    """Run (or hit the cache of) everything ``diffusion`` needs; load what generation uses."""
    from omegaconf import OmegaConf

    from gdwm.api import CommandError, run_pipeline
    from model_zoo.diffusion.rgbd_dual import RGBDDual
    from pipelines.data.reader import GSQADataset
    from pipelines.understanding.model import load_world_model

    run_cfg = OmegaConf.merge(cfg, {"targets": ["diffusion"]})
    summary = run_pipeline(run_cfg)
    if not summary.ok:
        raise CommandError(f"the pipeline up to diffusion did not finish: {summary.failed or summary.blocked}")
    res = summary.results
    model = RGBDDual.from_pretrained(res["diffusion"].path)
    model.eval()
    world = load_world_model(Path(res["lora"].path)) if model.cfg.high_level else None
    if world is not None:
        world.eval()
    return Runtime(
        GSQADataset(cfg.data.root),
        model,
        world,
        {s: Path(p) for s, (_, p) in res["reconstruct"].scenes.items()},
        {s: Path(p) for s, (_, p) in res["distill"].scenes.items()},
        res["diffusion"].key,
    )


def _condition(rt: Runtime, prompts: list) -> tuple[Any, Any]:
    """C_L for each prompt (``QASample``), padded; (None, None) when the high-level condition is off."""
    from pipelines.generation.examples import conditions_of, pad_tokens

    return pad_tokens(conditions_of(rt.world, rt.ds, rt.distill_dirs, prompts, len(prompts) or 1))


def _sample(rt: Runtime, examples: list, prompts: list, seed: int):
    import torch

    from pipelines.generation.samples import stack

    b = stack(examples)
    tok, mask = _condition(rt, prompts)
    gen = torch.Generator().manual_seed(seed)
    return rt.model.sample(b["ref_rgb"], b["ref_depth"], b["cond_rgb"], b["cond_depth"], b["cond_mask"], tok, mask,
                           generator=gen)  # fmt: skip


def _png(path: Path, rgb_3HW) -> None:
    import cv2
    import numpy as np

    img = (rgb_3HW.clamp(0, 1).permute(1, 2, 0).cpu().numpy() * 255).round().astype(np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR)):
        raise OSError(f"{path}: OpenCV could not write the image")


def _depth_png(path: Path, depth_HW, max_depth: float) -> None:
    import cv2
    import numpy as np

    d = (np.clip(depth_HW.cpu().numpy() / max_depth, 0, 1) * 255).astype(np.uint8)
    cv2.imwrite(str(path), cv2.applyColorMap(255 - d, cv2.COLORMAP_TURBO))


def write_mp4(path: Path, frames_3HW: list, fps: float) -> None:
    """An MP4 (OpenCV, mp4v) of ``[3, H, W]`` frames in [0, 1]."""
    import cv2
    import numpy as np

    h, w = frames_3HW[0].shape[1:]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    if not writer.isOpened():
        raise OSError(f"{path}: OpenCV could not open an MP4 writer (mp4v)")
    try:
        for f in frames_3HW:
            img = (f.clamp(0, 1).permute(1, 2, 0).cpu().numpy() * 255).round().astype(np.uint8)
            writer.write(cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    finally:
        writer.release()


def _log(cfg, kind: str, name: str, out_dir: Path, params: dict, metrics: dict) -> str:
    """One MLflow run (``gdwm.kind``) with every file of ``out_dir`` as artifacts; this process is the only writer."""
    from gdwm.api import TrackingBackend

    backend = TrackingBackend(cfg.tracking.uri, cfg.tracking.experiment, cfg.tracking.artifact_location)
    try:
        run_id = backend.create_run(name, {"gdwm.kind": kind})
        backend.log_params(run_id, params)
        if metrics:
            backend.log_metrics(run_id, metrics)
        for p in sorted(out_dir.rglob("*")):
            if p.is_file():
                backend.log_artifact(
                    run_id, str(p), str(p.parent.relative_to(out_dir)) if p.parent != out_dir else None
                )
        backend.end_run(run_id)
    finally:
        backend.close()
    return run_id


def generate(cfg, _argv: list[str]) -> int:
    """generate shifted / future views of a frame (args.scene, args.frame, args.shifts_m, args.horizons_s)"""
    from gdwm.api import console
    from pipelines.generation.conditions import horizon_frames
    from pipelines.generation.samples import GenTarget, build_example, frame_gaussians

    a = GenerateArgs(**cfg.args)
    scene = _require(a.scene, "args.scene")
    rt = _runtime(cfg)
    if scene not in rt.rec_dirs:
        from gdwm.api import CommandError

        raise CommandError(f"args.scene: no reconstruction of '{scene}' (scenes: {sorted(rt.rec_dirs)})")
    rate = float(rt.ds.scene(scene).info["frame_rate_hz"])
    targets = [GenTarget(scene, a.frame, a.camera, "shift", lateral_m=float(m)) for m in a.shifts_m]
    for s in a.horizons_s:
        h = horizon_frames(s, rate)
        targets.append(GenTarget(scene, a.frame, a.camera, "future", horizon_frames=h, horizon_s=float(s)))
    if not targets:
        from gdwm.api import CommandError

        raise CommandError("args.shifts_m and args.horizons_s are both empty: nothing to generate")
    gaussians = frame_gaussians(rt.rec_dirs[scene], scene, a.frame)
    synthetic = (rt.ds.root / "dataset.json").is_file() and json.loads((rt.ds.root / "dataset.json").read_text()).get(
        "source"
    ) == "synthetic_mini"
    examples = [build_example(rt.ds, t, gaussians, rt.model.cfg.image_size, edited=not synthetic and t.kind == "shift")
                for t in targets]  # fmt: skip
    rgb, depth = _sample(rt, examples, [t.qa() for t in targets], a.seed)
    out = Path(cfg.workdir) / "generated" / f"{scene}_{a.frame:03d}_{a.camera}"
    metrics = {}
    for i, t in enumerate(targets):
        _png(out / f"{t.name}.png", rgb[i])
        _depth_png(out / f"{t.name}_depth.png", depth[i], rt.model.cfg.max_depth)
        from pipelines.recon.losses import psnr

        metrics[f"gen/{t.name}/psnr"] = psnr(rgb[i].permute(1, 2, 0), examples[i].target_rgb.permute(1, 2, 0))
    write_mp4(out / "views.mp4", [r for r in rgb], a.fps)
    params = {"scene": scene, "frame": a.frame, "camera": a.camera, "diffusion_key": rt.diffusion_key}
    run_id = _log(cfg, "generate", f"generate {scene}/{a.frame}", out, params, metrics)
    console.print(f"wrote {len(targets)} views and views.mp4 to {out} (MLflow run {run_id})")
    for k, v in metrics.items():
        console.print(f"  {k} = {v:.2f} dB")
    return 0


def edit_region(cond_before, cond_after, threshold: float = 1e-3):
    """Pixels whose low-level conditions the edit changed (colour, depth or coverage), ``[B, H, W]`` bool."""
    diff = (cond_before["cond_rgb"] - cond_after["cond_rgb"]).abs().amax(1)
    diff = diff + (cond_before["cond_depth"] - cond_after["cond_depth"]).abs()
    diff = diff + (cond_before["cond_mask"] - cond_after["cond_mask"]).abs()
    return diff > threshold


def edit(cfg, _argv: list[str]) -> int:
    """edit a clip by instruction (args.edit: weather, remove/move/stop/insert a vehicle), then generate it"""
    import numpy as np
    import torch
    from scipy.ndimage import binary_dilation

    from gdwm.api import CommandError, console
    from pipelines.generation.edits import ReferenceFrame, Weather, edit_instruction, parse_edit
    from pipelines.generation.samples import GenTarget, build_example, edited_example, frame_gaussians, stack

    a = EditArgs(**cfg.args)
    scene = _require(a.scene, "args.scene")
    the_edit = parse_edit(_require(a.edit, "args.edit"))
    rt = _runtime(cfg)
    if scene not in rt.rec_dirs:
        raise CommandError(f"args.scene: no reconstruction of '{scene}' (scenes: {sorted(rt.rec_dirs)})")
    sc = rt.ds.scene(scene)
    rate = float(sc.info["frame_rate_hz"])
    frames = [f for f in range(a.frame, min(a.frame + a.frames, sc.num_frames))]
    ref_g = frame_gaussians(rt.rec_dirs[scene], scene, a.frame)
    poses = sc.ego_poses
    before, after, prompts_b, prompts_a = [], [], [], []
    for k, f in enumerate(frames):
        g = frame_gaussians(rt.rec_dirs[scene], scene, f)
        ref = ReferenceFrame(a.frame, ref_g, sc.frame(a.frame).boxes3d(), np.linalg.inv(poses[f]) @ poses[a.frame])
        t = GenTarget(scene, f, a.camera, "shift", lateral_m=0.0)
        ex_a, qa_a = edited_example(rt.ds, t, the_edit, g, sc.frame(f).boxes3d(), rt.model.cfg.image_size,
                                    t_s=k / rate, reference=ref)  # fmt: skip
        before.append(build_example(rt.ds, t, g, rt.model.cfg.image_size, edited=True))
        after.append(ex_a)
        prompts_b.append(t.qa())
        prompts_a.append(qa_a)
    # one seed for every clip: original (its Gaussians, no instruction), edited (edited Gaussians, instruction in
    # C_L) and, for geometry edits, the control (original Gaussians, instruction) that isolates the Gaussian edit
    rgb_o, _ = _sample(rt, before, prompts_b, a.seed)
    rgb_a, depth_a = _sample(rt, after, prompts_a, a.seed)
    geometry = not isinstance(the_edit, Weather)
    rgb_b = _sample(rt, before, prompts_a, a.seed)[0] if geometry else rgb_o
    slug = re.sub(r"[^0-9A-Za-z]+", "_", edit_instruction(the_edit)).strip("_").lower()[:60]
    out = Path(cfg.workdir) / "edits" / f"{scene}_{a.frame:03d}_{slug}"
    region = edit_region(stack(before), stack(after))
    if not geometry:
        region = torch.ones_like(region)
    # the Gaussian edit against the control (weather: against the original); the UNet's receptive field spreads a
    # local edit a little, so inside the region is compared to well outside it
    outside = torch.from_numpy(~binary_dilation(region.numpy(), iterations=8, axes=(1, 2)))
    delta = (rgb_a - rgb_b).abs().mean(1)
    inside_mean = float(delta[region].mean()) if bool(region.any()) else 0.0
    outside_mean = float(delta[outside].mean()) if bool(outside.any()) else 0.0
    for i, f in enumerate(frames):
        _png(out / f"edited_{f:03d}.png", rgb_a[i])
        _png(out / f"original_{f:03d}.png", rgb_o[i])
        _depth_png(out / f"edited_{f:03d}_depth.png", depth_a[i], rt.model.cfg.max_depth)
    write_mp4(out / "edited.mp4", list(rgb_a), a.fps)
    report = {
        "edit": edit_instruction(the_edit),
        "prompt": prompts_a[0].instruction,
        "frames": frames,
        "edited_pixels": int(region.sum()),
        "mean_abs_change_in_edited_region": inside_mean,
        "mean_abs_change_outside": outside_mean,
        "mean_abs_change_from_instruction": float(((rgb_b if geometry else rgb_a) - rgb_o).abs().mean()),
    }
    (out / "report.json").write_text(json.dumps(report, indent=2))
    metrics = {"edit/change_inside": inside_mean, "edit/change_outside": outside_mean,
               "edit/change_from_instruction": report["mean_abs_change_from_instruction"]}  # fmt: skip
    run_id = _log(cfg, "edit", f"edit {scene}/{a.frame}", out,
                  {"scene": scene, "frame": a.frame, "edit": report["edit"], "diffusion_key": rt.diffusion_key},
                  metrics)  # fmt: skip
    console.print(f"{report['edit']}: {len(frames)} frames to {out} (MLflow run {run_id})")
    console.print(f"  mean |change| inside the edited region {inside_mean:.4f}, outside {outside_mean:.4f}")
    return 0
