"""journal_ablation as one sweep (shared stages once, one cache) vs its five trials as independent ``gdwm run``s
with no shared cache, side by side in one run on a small synthetic_mini with tiny flavors.

The sweep side is the time the sweep says its trials took (``sweep: ... N s``): the table it then prints, with its
bootstrap intervals, is work the independent runs don't do."""

from __future__ import annotations

import re
import tempfile
from pathlib import Path

from benchmarks.common import TINY_FLAVORS, TINY_SCENES, Result
from benchmarks.common import gdwm as _gdwm
from gdwm.config import load_config
from gdwm.sweep import plan_sweep


def run(quick: bool = False) -> list[Result]:
    with tempfile.TemporaryDirectory(prefix="gdwm-bench-sweep-") as tmp:
        tmp = Path(tmp)
        data = [f"data.root={tmp / 'data'}", *TINY_SCENES]
        _gdwm("data", "synth", *data)  # one dataset: both sides read it
        base = [*data, *TINY_FLAVORS]
        t_total, out = _gdwm("sweep", "sweep=journal_ablation", f"workdir={tmp / 'sweep'}", *base)
        t_sweep = float(re.search(r"^sweep: .* (\d+) s$", out, re.MULTILINE).group(1))
        # the same trials, each as its own `gdwm run` in its own workdir (own cache, own store)
        argv = ["sweep=journal_ablation", *base, f"workdir={tmp / 'plan'}"]
        sweep, _, trials = plan_sweep(load_config(argv), argv)
        naive = sum(len(t.order) for t in trials)
        distinct = len({(n, t.keys[n]) for t in trials for n in t.order})
        t_runs = 0.0
        for i, t in enumerate(trials):
            targets = f"targets=[{','.join(sweep.targets)}]"
            run = _gdwm("run", targets, f"workdir={tmp / f'run{i}'}", *base, *sweep.overrides, *t.row.overrides)
            t_runs += run[0]
    ratio = t_sweep / t_runs
    detail = f"sweep {t_sweep:.0f} s (+{t_total - t_sweep:.0f} s table and report) vs 5 independent runs {t_runs:.0f} s"
    return [
        Result("sweep", "journal_ablation sweep / independent runs", ratio, "x", 0.5, "<=", detail),
        Result("sweep", "stage executions saved", float(naive - distinct), "", None, "<=",
               f"{distinct} distinct stage keys vs {naive} stage executions as independent runs"),
    ]  # fmt: skip
