"""Every numeric knob has its range in its schema (``gdwm.knobs``), checked when the config is composed: a value out
of range exits 2 naming the key, before anything launches."""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, field
from typing import Annotated

import pytest
from hydra.core.config_store import ConfigStore
from omegaconf import OmegaConf

from gdwm.cli import main
from gdwm.config import _register_all
from gdwm.knobs import Ge, Gt, Interval, Len, check_ranges, unranged


def _schemas() -> set[type]:
    """Every dataclass reachable from the schemas gdwm and its plugins register (hydra's own left out)."""
    _register_all()

    def nodes(repo: dict):
        for v in repo.values():
            yield from nodes(v) if isinstance(v, dict) else [OmegaConf.get_type(v.node)]

    found: set[type] = set()

    def add(cls: type) -> None:
        if cls in found or cls.__module__.startswith("hydra"):
            return
        found.add(cls)
        stack = list(typing.get_type_hints(cls, include_extras=True).values())
        while stack:
            h = stack.pop()
            if isinstance(h, type) and dataclasses.is_dataclass(h):
                add(h)
            stack += typing.get_args(h)

    for cls in nodes(ConfigStore.instance().repo):
        if isinstance(cls, type) and dataclasses.is_dataclass(cls):
            add(cls)
    return found


def test_every_numeric_knob_of_every_schema_declares_its_range():
    schemas = _schemas()
    names = {c.__name__ for c in schemas}
    assert {
        "RunSettings",
        "ClusterConfig",
        "StageResources",
        "LoraStageConfig",
        "SelectorConfig",
        "SynthConfig",
    } <= names
    assert {f"{c.__module__}.{c.__qualname__}": unranged(c) for c in schemas if unranged(c)} == {}


@pytest.mark.parametrize(
    "override, message",
    [
        ("seeds=[0,18446744073709551616]", "'seeds[1]': 18446744073709551616 (must be >= 0 and <= 4294967295)"),
        ("seed=18446744073709551616", "'seed': 18446744073709551616 (must be >= 0 and <= 4294967295)"),
        ("run.checkpoint_every=0", "'run.checkpoint_every': 0 (must be >= 1)"),
        ("run.max_retries=-1", "'run.max_retries': -1 (must be >= 0)"),
        ("run.max_failures=-2", "'run.max_failures': -2 (must be >= 0)"),
        ("cluster.connect_timeout_s=0", "'cluster.connect_timeout_s': 0.0 (must be > 0)"),
        ("cluster.num_cpus=0", "'cluster.num_cpus': 0 (must be >= 1)"),
        ("cluster.resources.train.num_cpus=0", "'cluster.resources.train.num_cpus': 0.0 (must be > 0)"),
        ("stage.lora.lr=nan", "'stage.lora.lr': nan (must be > 0)"),
        ("model.selector.uniform_fraction=1.5", "'model.selector.uniform_fraction': 1.5 (must be >= 0 and <= 1)"),
        ("tracking.experiment=" + "x" * 100_000,
         "'tracking.experiment': 'xxxxxxxxxxxxxxxxxxxx...' (100000 characters) (must be 1 to 256 characters)"),
    ],
)  # fmt: skip
def test_a_knob_out_of_range_exits_2_naming_the_key_before_anything_runs(override, message, tmp_path, capsys):
    rc = main(["run", "--dry-run", f"workdir={tmp_path}", override])
    err = capsys.readouterr().err
    assert rc == 2 and err.strip() == f"gdwm: config error: invalid value for {message}."
    assert list(tmp_path.iterdir()) == []  # nothing generated, nothing launched


@dataclass
class _Knobs:
    n: Annotated[int, Ge(1)] = 1
    xs: Annotated[list[float], Gt(0)] = field(default_factory=lambda: [1.0])
    by: Annotated[dict[str, float], Interval(ge=0, le=1)] = field(default_factory=dict)
    name: Annotated[str, Len(1, 8)] = "a"
    free: float = 0.0


def test_check_ranges_reads_every_element_and_value():
    cfg = OmegaConf.structured(_Knobs)
    assert check_ranges(cfg) is None and unranged(_Knobs) == ["free"]
    for change, bad in [({"xs": [1.0, -2.0]}, "'xs[1]': -2.0 (must be > 0)"),
                        ({"by": {"a": 0.5, "b": 2.0}}, "'by.b': 2.0 (must be >= 0 and <= 1)"),
                        ({"n": 0}, "'n': 0 (must be >= 1)"), ({"name": ""}, "'name': '' (must be 1 to 8 characters)"),
                        ({"xs": [float("inf")]}, "'xs[0]': inf (must be > 0)")]:  # fmt: skip
        assert check_ranges(OmegaConf.merge(cfg, change)) == f"invalid value for {bad}"
