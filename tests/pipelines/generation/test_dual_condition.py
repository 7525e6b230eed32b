"""Tab. world as the sweep builds it: every row trains without weather targets, on the conditions its label names."""

from __future__ import annotations

from omegaconf import OmegaConf

from gdwm.config import load_config
from pipelines.generation.config import DiffusionStageConfig
from pipelines.generation.examples import training_weathers


def test_every_dual_condition_row_resolves_with_weather_targets_off(tmp_path):
    assert training_weathers(DiffusionStageConfig()) == ["rain", "fog", "night"]  # the default trains on them
    sweep = load_config([f"workdir={tmp_path}", "sweep=dual_condition"]).sweep
    seen = {}
    for row in sweep.rows:
        cfg = load_config([f"workdir={tmp_path}", *sweep.overrides, *row.overrides])
        stage = OmegaConf.to_object(cfg.stage.diffusion)
        assert isinstance(stage, DiffusionStageConfig)
        assert stage.weather_targets is False, row.label
        assert training_weathers(stage) == [], row.label
        assert list(cfg.stage.evaluate_gen.shifts_m) == [1.0, -1.0], row.label  # the table is the ±1 m pool
        seen[row.label] = (cfg.model.diffusion.low_level, cfg.model.diffusion.high_level)
    assert seen == {"Low-level only": (True, False), "High-level only": (False, True), "Both": (True, True)}


def test_the_table_labels_the_fvd_stand_in_and_ranks_it_lower_is_better(tmp_path):
    from gdwm.compare.layout import resolve_columns

    layout = OmegaConf.to_object(load_config([f"workdir={tmp_path}", "compare=generation"]).compare)
    logged = ["gen/shift_pm1m/fd_video_daisy", "gen/shift_pm1m/fd_daisy", "gen/shift_pm1m/fvd"]
    cols = resolve_columns(layout, logged)
    assert [(c.header, c.direction.value) for c in cols] == [
        ("FD (daisy)", "lower"),
        ("FVD", "lower"),
        ("FVD stand-in (DAISY)", "lower"),
    ]
