"""A 3-seed ``journal_ablation`` sweep (seed-free reconstruction and distillation shared by the seeds, one cache)
vs the same table as three 1-seed sweeps (``seed=0``, ``1``, ``2``) with no shared cache, side by side in one run.
Each side is whole commands, its tables and reports included.

Default: the demo's settings (``experiment=demo``: synthetic_mini, 4 scenes). ``--quick``: 2 small scenes and the
tiny training flavors, a smoke run of the same comparison.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from benchmarks.common import TINY_FLAVORS, TINY_SCENES, Result
from benchmarks.common import gdwm as _gdwm
from gdwm.config import load_config
from gdwm.sweep import plan_sweep

SEEDS = (0, 1, 2)
QUICK = [*TINY_SCENES, *TINY_FLAVORS]


def _executions(argv: list[str]) -> tuple[int, int]:
    """(distinct stage keys, stage executions as independent trials) of the sweep ``argv`` plans."""
    _, _, trials = plan_sweep(load_config(argv), argv)
    return len({(n, t.keys[n]) for t in trials for n in t.order}), sum(len(t.order) for t in trials)


def run(quick: bool = False) -> list[Result]:
    with tempfile.TemporaryDirectory(prefix="gdwm-bench-seeds-") as tmp:
        tmp = Path(tmp)
        data = [f"data.root={tmp / 'data'}"]
        base = ["sweep=journal_ablation", *data, *(QUICK if quick else ["experiment=demo"])]
        _gdwm("data", "synth", *base[1:])  # one dataset: every side reads it
        seeds = f"seeds=[{','.join(map(str, SEEDS))}]"
        t_seeds = _gdwm("sweep", *base, seeds, f"workdir={tmp / 'seeds'}")[0]
        t_apart = [_gdwm("sweep", *base, f"seed={s}", f"workdir={tmp / f'seed{s}'}")[0] for s in SEEDS]
        together, _ = _executions([*base, seeds, f"workdir={tmp / 'seeds'}"])
        apart = sum(_executions([*base, f"seed={s}", f"workdir={tmp / 'plan'}"])[0] for s in SEEDS)
    ratio = t_seeds / sum(t_apart)
    detail = f"{t_seeds:.0f} s vs {' + '.join(f'{t:.0f}' for t in t_apart)} = {sum(t_apart):.0f} s"
    return [
        Result("seeds", "3-seed sweep / three 1-seed sweeps", ratio, "x", 0.8, "<=", detail),
        Result("seeds", "stage executions saved by sharing seed-free stages", float(apart - together), "", None, "<=",
               f"{together} distinct stage keys vs {apart} as three separate sweeps"),
    ]  # fmt: skip
