"""A launch's first idle worker imports what its stages will need (``gdwm.runner.warm_modules``)."""

from __future__ import annotations

import ray

from gdwm.dag import Pipeline
from gdwm.plan import PlanRow, Row, Trial
from gdwm.runner import import_modules, warm_modules
from tests.gdwm import stages as toy

ORDER = ["reconstruct", "distill", "tokenizer", "evaluate_qa"]
PIPE = Pipeline("toy", {n: getattr(toy, n) for n in ORDER}, ORDER)


def _trial(to_run: set[str]) -> Trial:
    plan = [PlanRow(n, None, f"k-{n}", "to run" if n in to_run else "cached", getattr(toy, n).resources) for n in ORDER]
    return Trial(Row(0, "toy", {}, [], [0]), 0, pipe=PIPE, order=ORDER, plan=plan)


def test_the_stages_to_run_and_training_where_one_trains():
    assert warm_modules([_trial({"distill", "tokenizer"})]) == ["tests.gdwm.stages", "gdwm.training"]
    assert warm_modules([_trial({"reconstruct"}), _trial({"evaluate_qa"})]) == ["tests.gdwm.stages"]


def test_nothing_when_every_stage_is_cached():
    assert warm_modules([_trial(set()), _trial(set())]) == []


def test_a_module_that_does_not_import_is_left_to_its_stage(ray_local):
    assert ray.get(import_modules.remote(["gdwm.no_such_module", "tests.gdwm.stages"])) == ["tests.gdwm.stages"]
