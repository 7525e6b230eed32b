"""``gdwm regress benchmark=NAME``: evaluate what a benchmark names, diff every metric against the baseline with its
direction and tolerance, log a ``gdwm.kind=regression`` run with the table and a trend plot, and exit 0 (no
regression), 1 (regression) or 2 (error) — what a nightly job needs to fail loudly, and only on real regressions.

A benchmark (``conf/benchmark/NAME.yaml``) names an experiment (overrides and targets; zoo references such as
``stage.lora.source=zoo:gdwm-lora@champion`` evaluate a registered version), the seeds it runs (one trial each; the
compared value is their mean), the metrics with their tolerances, and performance benchmarks (registered by name in
the entry-point group ``gdwm.benchmarks``) whose figures become metrics ``perf/<bench>/<metric>``.

A tolerance is a fixed amount (``tolerance: 1.0``, or a fraction with ``relative: true``), or the baseline's own
noise: ``tolerance: {sigma: 3}`` allows 3 standard deviations of the compared difference of two means over seeds,
Welch's ``sqrt(s_b^2/n_b + s_now^2/n_now)`` from both runs' spreads (``s_b * sqrt(1/n_b + 1/n_now)`` when now ran one
seed). With
``test: bootstrap`` a worsening is a regression only if a paired bootstrap over the held-out samples (both runs'
per-sample predictions, combined over seeds) finds it significant, beyond the tolerance.

The baseline is always a measured run: a reported row (``gdwm.kind=reference``, numbers copied from a paper) named
as ``benchmark.baseline`` is refused (exit 2). Numbers print rounded half up (``gdwm.compare.rounding``), as every
table of gdwm does, and the suites' aggregates (Avg.) are the one average of the printed values.
"""

from __future__ import annotations

import json
import math
import re
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf
from rich.table import Table

from gdwm.board import resampling_progress
from gdwm.compare.layout import Direction
from gdwm.compare.rounding import fmt_significant
from gdwm.config import BenchmarkConfig, CheckTest, ConfigError, MetricCheck, load_config, sqlite_path
from gdwm.names import check_name
from gdwm.term import console, err_console, verbosity

KIND = "regression"
BASELINE_TAG = "gdwm.baseline"


class RegressError(Exception):
    """The suite could not run (exit 2)."""


@dataclass
class Row:
    metric: str
    baseline: float | None
    now: float | None
    tolerance: str
    verdict: str  # ok | improved | REGRESSION | missing | new
    allowed: float | None = None
    """The tolerance as an amount of the metric (the trend plot's band around the baseline); None when unknown."""

    @property
    def delta(self) -> float | None:
        return None if self.baseline is None or self.now is None else self.now - self.baseline


Paired = Callable[[str], tuple[float, float] | None]
"""metric -> the (1 - alpha) bootstrap interval of (now - baseline), or None without per-sample data."""


def check(
    checks: list[MetricCheck], baseline: dict[str, float] | None, now: dict[str, float], paired: Paired | None = None
) -> list[Row]:
    """One row per watched metric; a metric missing now is a regression, one new to the suite is not.

    ``baseline`` and ``now`` hold means, with ``std/<metric>`` and ``n/<metric>`` over their seeds (what
    ``{sigma: K}`` scales); ``paired`` gives the bootstrap interval ``test: bootstrap`` needs."""
    rows = []
    for c in checks:
        b, n = (baseline or {}).get(c.name), now.get(c.name)
        arrow = " ↑" if c.direction == Direction.higher else " ↓"
        if c.sigma is not None:
            spread = _difference_spread(baseline or {}, now, c.name)
            tol = c.sigma * spread if spread is not None else math.nan
            shown = f"{c.sigma:g}σ" + (
                f" = {fmt_significant(tol, 3)}" if spread is not None else " (no spread)" if b is not None else ""
            )
        else:
            tol = c.tolerance * abs(b) if (c.relative and b is not None) else float(c.tolerance)
            shown = f"{c.tolerance:.0%}" if c.relative else f"{c.tolerance:g}"
        if c.test is CheckTest.bootstrap:
            shown += ", bootstrap"
        if n is None or (isinstance(n, float) and math.isnan(n)):
            verdict = "missing"
        elif b is None:
            verdict = "new"
        elif math.isnan(tol):
            verdict = "no spread"
        else:
            gain = (n - b) if c.direction == Direction.higher else (b - n)
            verdict = "REGRESSION" if gain < -tol - 1e-12 else "improved" if gain > 1e-12 else "ok"
            if verdict != "ok" and c.test is CheckTest.bootstrap:
                ci = paired(c.name) if paired is not None else None
                if ci is None:
                    verdict = "untestable"
                else:  # significant only when the interval of (now - baseline) excludes 0
                    lo, hi = ci if c.direction == Direction.higher else (-ci[1], -ci[0])
                    if (verdict == "REGRESSION" and hi >= 0) or (verdict == "improved" and lo <= 0):
                        verdict = "ok (not significant)"
        rows.append(Row(c.name, b, n, shown + arrow, verdict, None if math.isnan(tol) else tol))
    return rows


def _difference_spread(baseline: dict[str, float], now: dict[str, float], metric: str) -> float | None:
    """The standard error of (now's mean - the baseline's mean) over seeds: Welch's, from both runs' spreads, when
    both ran >= 2 seeds; from the baseline's spread alone when now ran one. None when the baseline has no spread.

    Both runs' seeds estimate the training noise: three seeds alone give a spread that is half the true one about
    one time in five, and a gate scaled by it alone would fire on other seeds of the same model that often."""
    s_b = baseline.get(f"std/{metric}")
    if s_b is None:
        return None
    n_b, n_n = baseline.get(f"n/{metric}", 1.0), now.get(f"n/{metric}", 1.0)
    s_n = now.get(f"std/{metric}")
    if s_n is None or n_n < 2:
        return s_b * math.sqrt(1 / n_b + 1 / n_n)
    return math.sqrt(s_b**2 / n_b + s_n**2 / n_n)


def failed(rows: list[Row]) -> list[Row]:
    """Rows that fail the suite: a regression, a metric gone, or a check that could not be made as configured."""
    return [r for r in rows if r.verdict in ("REGRESSION", "missing", "no spread", "untestable")]


BENCHMARK_GROUP = "gdwm.benchmarks"
"""Entry-point group of performance benchmarks: ``name = "module:run"``, ``run(quick: bool) -> list`` of results with
``metric`` and ``value``."""


def perf_metrics(names: list[str]) -> dict[str, float]:
    """Figures of the named performance benchmarks (quick mode) as ``perf/<bench>/<metric>`` metrics."""
    out = {}
    registered = {ep.name: ep for ep in entry_points(group=BENCHMARK_GROUP)} if names else {}
    for name in names:
        if name not in registered:
            raise RegressError(
                f"benchmark.perf: no performance benchmark '{name}' (entry-point group {BENCHMARK_GROUP} has: "
                f"{', '.join(sorted(registered)) or 'none'})"
            )
        ep = registered[name]
        try:
            run = ep.load()
        except ImportError as e:
            raise RegressError(
                f"benchmark.perf: performance benchmark '{name}' ({ep.value}) does not import: {e}"
            ) from e
        for r in run(quick=True):
            out[f"perf/{name}/{_slug(r.metric)}"] = float(r.value)
    return out


def _slug(text: str) -> str:
    return re.sub(r"[^a-z0-9_.-]+", "_", text.lower()).strip("_")


def load_benchmark(cfg: DictConfig) -> BenchmarkConfig:
    if cfg.get("benchmark") is None:
        raise RegressError("no benchmark selected: pass benchmark=NAME (conf/benchmark/)")
    try:
        bench = OmegaConf.to_object(cfg.benchmark)
    except ValueError as e:  # MetricCheck's own validation (the tolerance's form)
        raise RegressError(f"benchmark.metrics: {e}") from e
    try:  # its runs, reports and dashboards are filed under it
        check_name(bench.name, "benchmark.name")
    except ValueError as e:
        raise RegressError(str(e)) from None
    return bench


def regress(cfg: DictConfig, argv: list[str]) -> int:
    """Run the suite; 0 no regression, 1 regression (named), 2 error."""
    from gdwm.cache import CACHE_KEYS
    from gdwm.environment.record import environment
    from gdwm.environment.runs import baseline_flags as environment_flags
    from gdwm.environment.runs import tag_run
    from gdwm.plan import PlanError
    from gdwm.runner import aggregate, evaluation_metrics, evaluation_samples, run_pipeline
    from gdwm.tracking import TrackingBackend

    bench = load_benchmark(cfg)
    if not bench.metrics:
        raise RegressError(f"benchmark '{bench.name}': no metrics to watch (benchmark.metrics is empty): a gate that "
                           "checks nothing would always pass")  # fmt: skip
    # the suite's own keys (benchmark.*) are not the evaluated run's
    user = [a for a in argv if not a.startswith("--") and a.split("=", 1)[0].lstrip("+~").split(".")[0] != "benchmark"]
    overrides = [f"targets=[{','.join(bench.targets)}]", *bench.overrides, *user]
    try:
        overrides += honest_overrides(load_config(overrides), "--fresh" in argv)
        run_cfg = load_config(overrides)
    except ConfigError as e:
        raise RegressError(f"benchmark '{bench.name}' overrides: {e}") from e
    sigma = [c.name for c in bench.metrics if c.sigma is not None]
    n_seeds = len(run_cfg.seeds if run_cfg.get("seeds") is not None else bench.seeds or [run_cfg.seed])
    if sigma and n_seeds < 2:
        raise RegressError(
            f"benchmark '{bench.name}': {sigma[0]} has tolerance {{sigma: K}}, which needs >= 2 seeds "
            f"(benchmark.seeds has {n_seeds})"
        )
    backend, base_run = _baseline_before_launch(cfg, bench, "--set-baseline" in argv)
    if "--dry-run" in argv:
        return dry_run(cfg, bench, run_cfg, overrides)
    try:
        summary = run_pipeline(
            run_cfg, overrides, seeds=bench.seeds, seeds_key="benchmark.seeds", live=False, verbosity=verbosity(argv)
        )
    except PlanError as e:
        raise RegressError(f"benchmark '{bench.name}': {e}") from e
    if not summary.ok:
        raise RegressError(f"benchmark '{bench.name}': {'; '.join(summary.failed.values())}")
    per_seed = [evaluation_metrics(t.trial.pipe, t.results) for t in summary.trials]
    now = aggregate(per_seed) | perf_metrics(bench.perf)
    now_samples = {t.trial.seed: evaluation_samples(t.trial.pipe, t.results) for t in summary.trials}
    stages = provenance(summary.trials)

    if backend is None:  # the first run on a new store, recording the baseline
        backend = TrackingBackend(cfg.tracking.uri, cfg.tracking.experiment, cfg.tracking.artifact_location)
    paired = None
    if base_run and any(c.test is CheckTest.bootstrap for c in bench.metrics):
        with resampling_progress("gdwm regress", verbosity=verbosity(argv)):
            paired = _paired(backend, bench, base_run["run_id"], now_samples)
    rows = check(bench.metrics, base_run["metrics"] if base_run else None, now, paired)
    print_rows(bench, rows, base_run, [t.trial.seed for t in summary.trials])
    env = environment()
    flags = baseline_flags(backend, base_run["run_id"], stages) if base_run else []
    flags += environment_flags(backend, base_run["run_id"], env) if base_run else []
    print_provenance(stages, flags)
    run_id = backend.create_run(
        f"regress-{bench.name}",
        {"gdwm.kind": KIND, "gdwm.benchmark": bench.name, "gdwm.verdict": "fail" if failed(rows) else "pass",
         "gdwm.baseline_run": base_run["run_id"] if base_run else "",
         "gdwm.seeds": ",".join(str(t.trial.seed) for t in summary.trials)},
    )  # fmt: skip
    try:
        tag_run(backend, run_id, env)
        backend.log_metrics(run_id, now)
        backend.log_params(run_id, {"overrides": " ".join(bench.overrides + user), "targets": bench.targets})
        backend.log_text(run_id, markdown(rows), "regression.md")
        backend.log_text(run_id, json.dumps(checks_json(bench, rows), indent=1), CHECKS)
        backend.log_text(run_id, json.dumps(stages, indent=1, sort_keys=True), PROVENANCE)
        backend.log_text(run_id, json.dumps(_entry_keys(summary.trials), indent=1, sort_keys=True), CACHE_KEYS)
        if flags:
            backend.set_tags(run_id, {"gdwm.baseline_flag": "; ".join(flags)[:4000]})
        _log_samples(backend, run_id, now_samples)
        backend.set_tags(run_id, {"gdwm.commit": _commit()} if _commit() else {})
        with tempfile.TemporaryDirectory() as tmp:
            plot = trend_plot(backend, bench, now, Path(tmp) / "trend.png", rows, run_id, base_run)
            if plot is not None:
                backend.log_artifact(run_id, str(plot))
        if "--set-baseline" in argv:
            backend.set_tags(run_id, {BASELINE_TAG: "true"})
            console.print(f"recorded run {run_id} as the baseline of '{bench.name}'")
    finally:
        backend.end_run(run_id, "FINISHED")
    bad = failed(rows)
    console.print(f"regression run {run_id} ({'fail' if bad else 'pass'}; trend plot: its artifact trend.png)",
                  markup=False)  # fmt: skip
    for r in bad:
        why = "" if r.verdict in ("REGRESSION", "missing") else f": {r.verdict}"
        err_console.print(f"regression: {r.metric} {_fmt(r.baseline)} -> {_fmt(r.now)} (tolerance {r.tolerance}){why}",
                          markup=False)  # fmt: skip
    return 1 if bad and "--set-baseline" not in argv else 0


# ---- honesty: what was recomputed, and what the baseline was computed from --------------------------------------
PROVENANCE = "provenance.json"
"""Artifact of a regression run: ``{stage: {"status": ..., "code": digest}}`` over its trials."""
RECOMPUTED = "recomputed"


def honest_overrides(run_cfg: DictConfig, fresh: bool) -> list[str]:
    """The suite's evaluation targets always recompute (``cache.recompute``); stages whose code or libraries differ
    from the cached entries' re-run through their keys; ``--fresh`` recomputes everything (``cache.reuse=none``)."""
    from gdwm.dag import load_pipeline

    pipe = load_pipeline(run_cfg, list(run_cfg.targets) or None)
    order = pipe.ancestors(list(run_cfg.targets)) if run_cfg.targets else list(pipe.order)
    evaluation = [n for n in order if pipe.stages[n].evaluation]
    out = [f"cache.recompute=[{','.join(dict.fromkeys([*run_cfg.cache.recompute, *evaluation]))}]"]
    return out + ["cache.reuse=none"] * fresh


def provenance(trials: list) -> dict[str, dict[str, str]]:
    """Stage -> where its output came from in this run (the least trustworthy over the seeds) and its code digest."""
    from gdwm.executor import COMPUTED, least_trusted

    how: dict[str, list[str]] = {}
    code: dict[str, str] = {}
    for t in trials:
        for name, r in t.results.items():
            how.setdefault(name, []).append(COMPUTED if not r.cached else r.reused)
            code[name] = t.trial.settings.get("code", {}).get(name, {}).get("digest", "")
    out = {}
    for name, values in how.items():
        h = least_trusted(values)
        out[name] = {"status": RECOMPUTED if h == COMPUTED else f"reused ({h})", "code": code[name]}
    return out


def _entry_keys(trials: list) -> dict[str, list[str]]:
    from gdwm.runner import entry_keys

    out: dict[str, set[str]] = {}
    for t in trials:
        for name, keys in entry_keys(t.results).items():
            out.setdefault(name, set()).update(keys)
    return {n: sorted(k) for n, k in out.items()}


def baseline_flags(backend, base_id: str, now: dict[str, dict[str, str]]) -> list[str]:
    """What makes the baseline a weaker reference: stages it reused from other (or unknown) code, or no record of
    where its stages came from (recorded by an older gdwm)."""
    try:
        with tempfile.TemporaryDirectory() as tmp:
            path = backend.client.download_artifacts(base_id, PROVENANCE, tmp)
            base = json.loads(Path(path).read_text())
    except Exception:
        return [f"baseline run {base_id[:12]} has no record of the code its stages ran (an older gdwm); re-record "
                "it with --set-baseline --fresh"]  # fmt: skip
    other = [n for n, p in base.items() if p.get("status") not in (RECOMPUTED, "reused (same code)")]
    flags = []
    if other:
        flags.append(f"baseline run {base_id[:12]}: {', '.join(other)} came from other code than the baseline's "
                     "(cache.reuse=all); re-record it with --set-baseline --fresh")  # fmt: skip
    changed = [n for n in now if n in base and base[n].get("code") != now[n]["code"]]
    if changed:
        flags.append(f"code changed since the baseline: {', '.join(changed)} (recomputed here)")
    return flags


def print_provenance(stages: dict[str, dict[str, str]], flags: list[str]) -> None:
    t = Table(title="stages", header_style="bold")
    for col in ("stage", "output", "code"):
        t.add_column(col)
    for name, p in stages.items():
        t.add_row(name, p["status"], p["code"][:12])
    console.print(t)
    for f in flags:
        console.print(f"[yellow]{f}[/yellow]", markup=True)


SAMPLES_DIR = "samples"
"""Where a regression run keeps its trials' per-sample tables: ``samples/<stage>/seed_<N>.parquet``."""


def _log_samples(backend, run_id: str, samples: dict[int, dict]) -> None:
    """Each seed's per-sample tables and how to rescore them (``gdwm.scorer.<stage>``, ``gdwm.strata.<stage>``):
    what a later run's bootstrap test compares against when this run is its baseline."""
    tags = {}
    with tempfile.TemporaryDirectory() as tmp:
        for seed, stages in samples.items():
            for stage, smp in stages.items():
                named = Path(tmp) / stage / f"seed_{seed}{smp.path.suffix}"
                named.parent.mkdir(parents=True, exist_ok=True)
                named.write_bytes(smp.path.read_bytes())
                backend.log_artifact(run_id, str(named), f"{SAMPLES_DIR}/{stage}")
                tags |= {k: v for k, v in smp.tags(stage, f"{SAMPLES_DIR}/{stage}").items()}
    if tags:
        backend.set_tags(run_id, tags)


def _paired(backend, bench: BenchmarkConfig, base_id: str, now: dict[int, dict]) -> Paired:
    """metric -> interval of (now - baseline): a paired bootstrap over the held-out samples both runs answered, each
    side the mean over its seeds (``gdwm.compare.stats``)."""
    from gdwm.compare.samples import quiet_downloads, sample_set, scorer
    from gdwm.compare.stats import Settings, paired_bootstrap

    tags = backend.client.get_run(base_id).data.tags
    settings = Settings(alpha=bench.alpha, confidence=1 - bench.alpha, n_resamples=bench.resamples)
    metrics = [c.name for c in bench.metrics if c.test is CheckTest.bootstrap]
    out: dict[str, tuple[float, float]] = {}
    stages = sorted({st for per in now.values() for st in per})
    with tempfile.TemporaryDirectory() as tmp, quiet_downloads():
        for stage in stages:
            spec = tags.get(f"gdwm.scorer.{stage}")
            files = backend.client.list_artifacts(base_id, f"{SAMPLES_DIR}/{stage}") if spec else []
            if not files:
                continue
            fn, strata = scorer(spec), tags.get(f"gdwm.strata.{stage}")
            base = [
                sample_set(backend.client.download_artifacts(base_id, f.path, tmp), fn, strata, f.path) for f in files
            ]
            mine = [
                sample_set(per[stage].path, fn, strata, str(per[stage].path)) for per in now.values() if stage in per
            ]
            b = paired_bootstrap(stage, {0: base, 1: mine}, metrics, settings, {0: "baseline", 1: "now"})
            if b is not None:
                out |= {m: (-hi, -lo) for (_, _, m), (lo, hi) in b.diffs.items()}  # diffs are baseline - now
    return out.get


def _baseline_before_launch(cfg: DictConfig, bench: BenchmarkConfig, setting: bool) -> tuple[Any, dict | None]:
    """``(backend, baseline run)`` read before anything runs: a baseline id that does not exist, or no baseline at all
    unless this run records one (``--set-baseline``), is a ``RegressError`` (exit 2). A sqlite store that does not
    exist yet is not created (``backend`` None)."""
    from gdwm.config import sqlite_path
    from gdwm.tracking import TrackingBackend

    db = sqlite_path(cfg.tracking.uri)
    backend = base_run = None
    if db is None or Path(db).is_file():
        backend = TrackingBackend(cfg.tracking.uri, cfg.tracking.experiment, cfg.tracking.artifact_location)
        base_run = _baseline(backend, bench)
    elif bench.baseline:
        raise RegressError(f"benchmark.baseline: no run '{bench.baseline}' in {cfg.tracking.uri} (no store there)")
    if base_run is None and not setting:
        raise RegressError(
            f"benchmark '{bench.name}': no baseline in {cfg.tracking.uri} (no run of it tagged {BASELINE_TAG}=true, "
            f"no benchmark.baseline): record one first with gdwm regress benchmark={bench.name} --set-baseline"
        )
    return backend, base_run


def _baseline(backend, bench: BenchmarkConfig) -> dict | None:
    """The baseline run's id and metrics: ``benchmark.baseline``, else the suite's latest run tagged as baseline
    (a regression run, never a reported row)."""
    from gdwm.compare.runs import REFERENCE_KIND

    if bench.baseline:
        try:
            run = backend.client.get_run(bench.baseline)
        except Exception as e:
            raise RegressError(f"benchmark.baseline: no run '{bench.baseline}' in {backend.uri}") from e
        if run.data.tags.get("gdwm.kind") == REFERENCE_KIND:
            raise RegressError(
                f"benchmark.baseline={bench.baseline}: a reported row (gdwm.kind={REFERENCE_KIND}, numbers copied "
                f"from {run.data.tags.get('gdwm.source.paper') or 'a paper'}) cannot be a regression baseline; name "
                "a measured run, or record one with --set-baseline"
            )
        return {"run_id": run.info.run_id, "metrics": dict(run.data.metrics)}
    found = backend.search_runs(
        f"tags.`gdwm.kind` = '{KIND}' and tags.`gdwm.benchmark` = '{bench.name}' and tags.`{BASELINE_TAG}` = 'true'",
        1,
        order_by=["attributes.start_time DESC"],
    )
    return {"run_id": found[0]["run_id"], "metrics": found[0]["metrics"]} if found else None


def _fmt(v: float | None) -> str:
    return "–" if v is None else fmt_significant(v, 4)


def _signed(v: float) -> str:
    return ("+" if v >= 0 else "") + fmt_significant(v, 4)


def print_rows(bench: BenchmarkConfig, rows: list[Row], base_run: dict | None, seeds: list[int]) -> None:
    where = f"baseline run {base_run['run_id'][:12]}" if base_run else "no baseline yet (--set-baseline records one)"
    mean = f", mean of seeds {seeds}" if len(seeds) > 1 else ""
    # a line of its own, not the table's title: a title wraps to the table's width and splits what a log is grepped for
    console.print(f"regression '{bench.name}' vs {where}{mean}", markup=False)
    t = Table(header_style="bold")
    for col in ("metric", "baseline", "now", "delta", "tolerance", "verdict"):
        t.add_column(col)
    style = {"REGRESSION": "red", "missing": "red", "no spread": "red", "untestable": "red", "improved": "green"}
    for r in rows:
        d = "–" if r.delta is None else _signed(r.delta)
        v = f"[{style[r.verdict]}]{r.verdict}[/{style[r.verdict]}]" if r.verdict in style else r.verdict
        t.add_row(r.metric, _fmt(r.baseline), _fmt(r.now), d, r.tolerance, v)
    console.print(t)


CHECKS = "regression.json"
"""Artifact of a regression run: every check as data (the dashboard draws the baseline and its band from it)."""


def checks_json(bench: BenchmarkConfig, rows: list[Row]) -> list[dict]:
    """Per check: metric, direction, baseline, now, tolerance (as printed), allowed (the band's half-width in the
    metric's units; null when unknown) and verdict."""
    direction = {c.name: Direction(c.direction).value for c in bench.metrics}
    return [{"metric": r.metric, "direction": direction.get(r.metric, "higher"), "baseline": r.baseline, "now": r.now,
             "tolerance": r.tolerance, "allowed": r.allowed, "verdict": r.verdict} for r in rows]  # fmt: skip


def markdown(rows: list[Row]) -> str:
    lines = ["| metric | baseline | now | delta | tolerance | verdict |", "|---|---|---|---|---|---|"]
    for r in rows:
        d = "–" if r.delta is None else _signed(r.delta)
        lines.append(f"| {r.metric} | {_fmt(r.baseline)} | {_fmt(r.now)} | {d} | {r.tolerance} | {r.verdict} |")
    return "\n".join(lines) + "\n"


def _commit() -> str:
    """The commit of the checkout gdwm runs from (empty outside a git checkout): the trend plot's x labels."""
    import subprocess

    try:
        out = subprocess.run(["git", "rev-parse", "--short=10", "HEAD"], cwd=Path(__file__).parent, capture_output=True,
                             text=True, timeout=10)  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return ""
    return out.stdout.strip() if out.returncode == 0 else ""


def trend_plot(backend, bench: BenchmarkConfig, now: dict[str, float], path: Path, rows: list[Row] | None = None,
               run_id: str | None = None, base_run: dict | None = None) -> Path | None:  # fmt: skip
    """Each watched metric over this suite's regression runs, oldest first, this run last (once), each point labelled
    with its date and commit; the baseline as a line with its tolerance band, the baseline run's point ringed."""
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
    past = [r for r in past if r["run_id"] != run_id]  # this run is drawn once, from `now`
    labels = [f"{time.strftime('%m-%d %H:%M', time.localtime(r['start_time'] / 1000))}\n"
              f"{r['tags'].get('gdwm.commit', '')[:7]}" for r in past]  # fmt: skip
    labels.append(f"{time.strftime('%m-%d %H:%M')}\n{_commit()[:7]} (now)")
    by_metric = {r.metric: r for r in rows or []}
    cols = min(3, len(names))
    nrows = math.ceil(len(names) / cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(4.5 * cols, 3.2 * nrows), squeeze=False)
    for ax, name in zip(axes.flat, names, strict=False):
        ys = [r["metrics"].get(name, math.nan) for r in past] + [now.get(name, math.nan)]
        xs = list(range(len(ys)))
        ax.plot(xs, ys, marker="o")
        r = by_metric.get(name)
        if r is not None and r.baseline is not None:
            ax.axhline(r.baseline, color="gray", linestyle="--", linewidth=1, label="baseline")
            if r.allowed is not None:
                ax.axhspan(r.baseline - r.allowed, r.baseline + r.allowed, color="gray", alpha=0.15,
                           label=f"tolerance {r.tolerance}")  # fmt: skip
            at = [i for i, p in enumerate(past) if base_run and p["run_id"] == base_run["run_id"]]
            if at:
                ax.plot(at, [ys[i] for i in at], marker="o", markersize=11, fillstyle="none", color="black",
                        linestyle="none")  # fmt: skip
            ax.legend(fontsize=7)
        ax.set_title(name, fontsize=9)
        ax.set_xticks(xs, labels, fontsize=6, rotation=45, ha="right")
    for ax in list(axes.flat)[len(names) :]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


def dry_run(cfg: DictConfig, bench: BenchmarkConfig, run_cfg: DictConfig, overrides: list[str]) -> int:
    """``--dry-run``: the plan (what would run, what is cached and why stages re-run), the baseline and every check
    with its tolerance; nothing runs and nothing is logged."""
    from gdwm.plan import PlanError
    from gdwm.runner import run_pipeline
    from gdwm.tracking import TrackingBackend

    try:
        run_pipeline(run_cfg, overrides, seeds=bench.seeds, seeds_key="benchmark.seeds", dry_run=True)
    except PlanError as e:
        raise RegressError(f"benchmark '{bench.name}': {e}") from e
    base_run = None
    if (db := sqlite_path(cfg.tracking.uri)) is None or Path(db).is_file():
        base_run = _baseline(TrackingBackend(cfg.tracking.uri, cfg.tracking.experiment,
                                             cfg.tracking.artifact_location), bench)  # fmt: skip
    where = f"baseline run {base_run['run_id']}" if base_run else "no baseline yet (--set-baseline records one)"
    t = Table(title=f"regression '{bench.name}' would compare with {where}", header_style="bold")
    for col in ("metric", "baseline", "tolerance", "test"):
        t.add_column(col)
    for c in bench.metrics:
        b = base_run["metrics"].get(c.name) if base_run else None
        tol = f"{c.sigma:g}σ" if c.sigma is not None else f"{c.tolerance:.0%}" if c.relative else f"{c.tolerance:g}"
        t.add_row(c.name + (" ↑" if c.direction == Direction.higher else " ↓"), _fmt(b), tol, str(c.test.value))
    console.print(t)
    console.print("dry run: nothing ran, nothing was logged", markup=False)
    return 0
