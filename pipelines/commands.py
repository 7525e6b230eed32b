"""The ``gdwm data`` commands that build and export the pipelines' datasets (entry point ``gdwm.commands``, name
``data``: a mapping of subcommands). Light on purpose: gdwm reads it on every start to list its commands."""

from __future__ import annotations

from omegaconf import DictConfig

from gdwm.api import Command, build_data, console, err_console


def export_release(cfg: DictConfig, _args: list[str]) -> int:
    """``gdwm data export-gaussiandwm``: the dataset at ``data.root`` in the GaussianDWM release's format."""
    if not cfg.args.out:
        err_console.print("gdwm data export-gaussiandwm: args.out=DIR is required (the folder to write)", markup=False)
        return 2
    from pipelines.data.gaussiandwm_export import export

    summary = export(cfg.data.root, cfg.args.out, cfg.args.gaussians, overwrite=cfg.overwrite)
    for line in summary.lines():
        console.print(line, markup=False, soft_wrap=True)
    return 0


DATA: dict[str, Command] = {
    "synth": Command(build_data, "generate the synthetic_mini dataset (data.num_scenes, data.seed, ...)"),
    "import-gaussiandwm": Command(
        build_data, "import the public GaussianDWM release from source=DIR", ["data=gaussiandwm_release"]
    ),
    "export-gaussiandwm": Command(
        export_release,
        "write the dataset selected by data=... in the GaussianDWM release's format to args.out=DIR "
        "(args.gaussians=DIR: per-frame Gaussians of a dataset without them, <scene_id>/gaussians/<frame>.arrow)",
        ["+args.out=null", "+args.gaussians=null"],
    ),
    "convert-nuscenes": Command(build_data, "convert nuScenes v1.0 tables on disk at source=DIR", ["data=nuscenes"]),
    "import-nuinteract": Command(
        build_data,
        "attach NuInteract's released QA at source=DIR to the converted nuScenes dataset (data.nuscenes=...)",
        ["data=nuinteract"],
    ),
    "import-nuinstruct": Command(
        build_data,
        "attach NuInstruct's released QA at source=DIR to the converted nuScenes dataset (data.nuscenes=...)",
        ["data=nuinstruct"],
    ),
    "import-omnidrive": Command(
        build_data,
        "attach OmniDrive's released QA at source=DIR to the converted nuScenes dataset (data.nuscenes=...)",
        ["data=omnidrive"],
    ),
}
"""Subcommands of ``gdwm data``, listed in this order (before gdwm's own ``info``). Each data option's
``build_command`` names the one that builds it, for gdwm's messages about a missing or mismatched dataset."""
