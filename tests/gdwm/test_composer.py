"""Trials' configs composed once per set of group choices: the same config and the same errors as ``load_config``."""

from __future__ import annotations

from pathlib import Path

import pytest
from omegaconf import OmegaConf

from gdwm.composer import Composer, split_overrides
from gdwm.config import ConfigError, load_config

BASE = ["experiment=toy", "workdir=/tmp/gdwm-composer-test", "run.live=false"]


@pytest.fixture(autouse=True)
def toy_conf(monkeypatch):
    monkeypatch.setenv("GDWM_CONF_PATH", str(Path(__file__).parents[1] / "conf"))


def _load(f) -> object:
    try:
        return OmegaConf.to_container(f())
    except ConfigError as e:
        return ("ConfigError", str(e))


def test_split_tells_group_choices_from_values():
    groups, values = split_overrides(["stage.toy_lora.rank=8", "model/selector=voxel_topk", "cluster=sim", "seed=2",
                                      "+stage.extra.x=1", "~stage.toy_lora.steps"])  # fmt: skip
    assert groups == ["model/selector=voxel_topk", "cluster=sim"]
    assert [v.input_line for v in values] == ["stage.toy_lora.rank=8", "seed=2", "+stage.extra.x=1",
                                              "~stage.toy_lora.steps"]  # fmt: skip
    assert split_overrides(["stage.toy_lora.rank=[1,"]) is None  # the full composition says what is wrong


def test_a_trial_config_is_load_configs_and_so_is_its_error():
    composer = Composer(BASE)
    for extra in (
        ["stage.toy_lora.rank=8", "seed=1"],
        ["cluster=sim", "stage.toy_lora.rank=2", "+stage.toy_lora.note=x"],  # a group choice, an added key
        ["stage.toy_lora.rnak=8"],  # a typo: the same error, naming the key
        ["+stage.toy_lora.rank=3"],  # adds a key that exists
        ["stage.toy_lora.rank=[1,"],  # does not parse
    ):
        assert _load(lambda e=extra: composer.load(e)) == _load(lambda e=extra: load_config([*BASE, *e])), extra


def test_value_only_trials_compose_once():
    composer = Composer(BASE)
    cfgs = [composer.load([f"stage.toy_lora.rank={r}", f"seed={s}"]) for r in (2, 4, 8) for s in (0, 1)]
    assert [(c.stage.toy_lora.rank, c.seed) for c in cfgs] == [(r, s) for r in (2, 4, 8) for s in (0, 1)]
    assert composer.compositions == 1
    composer.load(["stage/reconstruct=tiny", "seed=0"])
    composer.load(["stage/reconstruct=tiny", "seed=1"])
    assert composer.compositions == 2  # one more for the new group choice, shared by its seeds
    assert cfgs[0].stage.toy_lora.rank == 2  # each trial has its own copy
