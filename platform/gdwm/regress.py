"""``gdwm regress benchmark=NAME``: evaluate what a benchmark names, diff every metric against the baseline with its
direction and tolerance, log a ``gdwm.kind=regression`` run with the table and a trend plot, and exit 0 (no
regression), 1 (regression) or 2 (error) — what a nightly job needs to fail loudly.

A benchmark (``conf/benchmark/NAME.yaml``) names an experiment (overrides and targets; zoo references such as
``stage.lora.source=zoo:gdwm-lora@champion`` evaluate a registered version), the metrics with their tolerances, and
performance benchmarks from ``benchmarks/`` whose figures become metrics ``perf/<bench>/<metric>``.
"""

from __future__ import annotations

import importlib
import math
import re
import sys
import tempfile
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path

from omegaconf import MISSING, DictConfig, OmegaConf
from rich.table import Table

from gdwm.config import ConfigError, conf_dir, load_config
from gdwm.term import console, err_console

KIND = "regression"
BASELINE_TAG = "gdwm.baseline"


class Direction(StrEnum):
    higher = "higher"
    lower = "lower"


@dataclass
class MetricCheck:
    """One watched metric."""

    name: str = MISSING
    """Metric name as logged (``nuinteract/avg``, ``perf/select/...``)."""
    direction: Direction = Direction.higher
    """Which way is better."""
    tolerance: float = 0.0
    """Allowed worsening before it is a regression."""
    relative: bool = False
    """``tolerance`` is a fraction of the baseline value instead of an absolute amount."""


@dataclass
class BenchmarkConfig:
    """A regression suite (group ``benchmark/``)."""

    name: str = MISSING
    """Suite name: its runs are tagged ``gdwm.benchmark=<name>``."""
    overrides: list[str] = field(default_factory=list)
    """What to evaluate: overrides of ``gdwm run`` (an experiment, zoo references)."""
    targets: list[str] = field(default_factory=lambda: ["evaluate_qa"])
    """Stages whose evaluation metrics are compared."""
    metrics: list[MetricCheck] = field(default_factory=list)
    """The watched metrics."""
    perf: list[str] = field(default_factory=list)
    """Performance benchmarks from ``benchmarks/`` (run with ``--quick``); their figures become ``perf/...``."""
    baseline: str | None = None
    """A run id to compare against; default: the latest run of this suite tagged as baseline."""


class RegressError(Exception):
    """The suite could not run (exit 2)."""


@dataclass
class Row:
    metric: str
    baseline: float | None
    now: float | None
    tolerance: str
    verdict: str  # ok | improved | REGRESSION | missing | new

    @property
    def delta(self) -> float | None:
        return None if self.baseline is None or self.now is None else self.now - self.baseline


def check(checks: list[MetricCheck], baseline: dict[str, float] | None, now: dict[str, float]) -> list[Row]:
    """One row per watched metric; a metric missing now is a regression, one new to the suite is not."""
    rows = []
    for c in checks:
        b, n = (baseline or {}).get(c.name), now.get(c.name)
        tol = c.tolerance * abs(b) if (c.relative and b is not None) else c.tolerance
        shown = f"{c.tolerance:.0%}" if c.relative else f"{c.tolerance:g}"
        shown += " ↑" if c.direction == Direction.higher else " ↓"
        if n is None or (isinstance(n, float) and math.isnan(n)):
            verdict = "missing"
        elif b is None:
            verdict = "new"
        else:
            gain = (n - b) if c.direction == Direction.higher else (b - n)
            verdict = "REGRESSION" if gain < -tol - 1e-12 else "improved" if gain > 1e-12 else "ok"
        rows.append(Row(c.name, b, n, shown, verdict))
    return rows


def failed(rows: list[Row]) -> list[Row]:
    return [r for r in rows if r.verdict in ("REGRESSION", "missing")]


def perf_metrics(names: list[str]) -> dict[str, float]:
    """Figures of ``benchmarks/`` (quick mode) as ``perf/<bench>/<metric>`` metrics."""
    out = {}
    root = str(conf_dir().parent)  # benchmarks/ sits next to conf/ in a checkout (and in the k8s image)
    if names and root not in sys.path:
        sys.path.append(root)
    for name in names:
        try:
            mod = importlib.import_module(f"benchmarks.bench_{name}")
        except ImportError as e:
            raise RegressError(
                f"benchmark.perf: performance benchmark '{name}' (benchmarks/bench_{name}.py under {root}) does not "
                f"import: {e}"
            ) from e
        for r in mod.run(quick=True):
            out[f"perf/{name}/{_slug(r.metric)}"] = float(r.value)
    return out


def _slug(text: str) -> str:
    return re.sub(r"[^a-z0-9_.-]+", "_", text.lower()).strip("_")


def load_benchmark(cfg: DictConfig) -> BenchmarkConfig:
    if cfg.get("benchmark") is None:
        raise RegressError("no benchmark selected: pass benchmark=NAME (conf/benchmark/)")
    return OmegaConf.to_object(cfg.benchmark)


def regress(cfg: DictConfig, argv: list[str]) -> int:
    """Run the suite; 0 no regression, 1 regression (named), 2 error."""
    from gdwm.runner import evaluation_metrics, run_pipeline
    from gdwm.tracking import TrackingBackend

    bench = load_benchmark(cfg)
    user = [a for a in argv if not a.startswith("--") and a.split("=", 1)[0] != "benchmark"]
    try:
        run_cfg = load_config([f"targets=[{','.join(bench.targets)}]", *bench.overrides, *user])
    except ConfigError as e:
        raise RegressError(f"benchmark '{bench.name}' overrides: {e}") from e
    summary = run_pipeline(run_cfg, live=False)
    if summary.failed:
        raise RegressError(f"benchmark '{bench.name}': {'; '.join(summary.failed.values())}")
    from gdwm.dag import load_pipeline

    now = evaluation_metrics(load_pipeline(run_cfg, list(run_cfg.targets)), summary.results)
    now |= perf_metrics(bench.perf)

    backend = TrackingBackend(cfg.tracking.uri, cfg.tracking.experiment, cfg.tracking.artifact_location)
    base_run = _baseline(backend, bench)
    rows = check(bench.metrics, base_run["metrics"] if base_run else None, now)
    print_rows(bench, rows, base_run)
    run_id = backend.create_run(
        f"regress-{bench.name}",
        {"gdwm.kind": KIND, "gdwm.benchmark": bench.name, "gdwm.verdict": "fail" if failed(rows) else "pass",
         "gdwm.baseline_run": base_run["run_id"] if base_run else ""},
    )  # fmt: skip
    try:
        backend.log_metrics(run_id, now)
        backend.log_params(run_id, {"overrides": " ".join(bench.overrides + user), "targets": bench.targets})
        backend.log_text(run_id, markdown(rows), "regression.md")
        with tempfile.TemporaryDirectory() as tmp:
            plot = trend_plot(backend, bench, now, Path(tmp) / "trend.png")
            if plot is not None:
                backend.log_artifact(run_id, str(plot))
        if "--set-baseline" in argv:
            backend.set_tags(run_id, {BASELINE_TAG: "true"})
            console.print(f"recorded run {run_id} as the baseline of '{bench.name}'")
    finally:
        backend.end_run(run_id, "FINISHED")
    bad = failed(rows)
    for r in bad:
        err_console.print(f"regression: {r.metric} {_fmt(r.baseline)} -> {_fmt(r.now)} (tolerance {r.tolerance})",
                          markup=False)  # fmt: skip
    return 1 if bad and "--set-baseline" not in argv else 0


def _baseline(backend, bench: BenchmarkConfig) -> dict | None:
    if bench.baseline:
        try:
            run = backend.client.get_run(bench.baseline)
        except Exception as e:
            raise RegressError(f"benchmark.baseline: no run '{bench.baseline}' in {backend.uri}") from e
        return {"run_id": run.info.run_id, "metrics": dict(run.data.metrics)}
    found = backend.search_runs(
        f"tags.`gdwm.kind` = '{KIND}' and tags.`gdwm.benchmark` = '{bench.name}' and tags.`{BASELINE_TAG}` = 'true'",
        1,
        order_by=["attributes.start_time DESC"],
    )
    return {"run_id": found[0]["run_id"], "metrics": found[0]["metrics"]} if found else None


def _fmt(v: float | None) -> str:
    return "–" if v is None else f"{v:.4g}"


def print_rows(bench: BenchmarkConfig, rows: list[Row], base_run: dict | None) -> None:
    where = f"baseline run {base_run['run_id'][:12]}" if base_run else "no baseline yet (--set-baseline records one)"
    t = Table(title=f"regression '{bench.name}' vs {where}", header_style="bold")
    for col in ("metric", "baseline", "now", "delta", "tolerance", "verdict"):
        t.add_column(col)
    style = {"REGRESSION": "red", "missing": "red", "improved": "green"}
    for r in rows:
        d = "–" if r.delta is None else f"{r.delta:+.4g}"
        v = f"[{style[r.verdict]}]{r.verdict}[/{style[r.verdict]}]" if r.verdict in style else r.verdict
        t.add_row(r.metric, _fmt(r.baseline), _fmt(r.now), d, r.tolerance, v)
    console.print(t)


def markdown(rows: list[Row]) -> str:
    lines = ["| metric | baseline | now | delta | tolerance | verdict |", "|---|---|---|---|---|---|"]
    for r in rows:
        d = "–" if r.delta is None else f"{r.delta:+.4g}"
        lines.append(f"| {r.metric} | {_fmt(r.baseline)} | {_fmt(r.now)} | {d} | {r.tolerance} | {r.verdict} |")
    return "\n".join(lines) + "\n"


def trend_plot(backend, bench: BenchmarkConfig, now: dict[str, float], path: Path) -> Path | None:
    """Each watched metric over this suite's past regression runs (oldest first), the current run last."""
    names = [c.name for c in bench.metrics]
    if not names:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    past = backend.search_runs(
        f"tags.`gdwm.kind` = '{KIND}' and tags.`gdwm.benchmark` = '{bench.name}'",
        200,
        order_by=["attributes.start_time ASC"],
    )
    cols = min(3, len(names))
    rows = math.ceil(len(names) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 2.6 * rows), squeeze=False)
    for ax, name in zip(axes.flat, names, strict=False):
        ys = [r["metrics"].get(name, math.nan) for r in past] + [now.get(name, math.nan)]
        ax.plot(range(len(ys)), ys, marker="o")
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("regression run")
    for ax in list(axes.flat)[len(names) :]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path
