"""What a sweep costs per trial as it grows, on a workdir's sqlite store and on a team's store, side by side in one run.

Toy sweeps of no-op stages (``benchmarks/noop_stages.py``: ``prep`` shared by every trial, ``fit`` and ``score`` per
trial, each a file write) of 1, 10, 50 and 200 trials, each a ``gdwm sweep`` in its own process on a fresh cache:
first on the embedded store (``sqlite:///<workdir>/mlflow.db``, written by the tracking actor), then on MLflow with
basic-auth on PostgreSQL and artifacts on S3 (``tests/gdwm/servers.py``: PostgreSQL with fsync on, moto, one
uvicorn worker), one server for every size (a store that fills as a team's does). Per size and store:

- wall time per trial, the cost a trial adds beyond the launch's fixed start-up: ``(T(N) - T(1)) / (N - 1)``, T being
  the time the sweep reports for its trials (``sweep: ... N s``; the report that follows is timed as compare);
- the driver's peak RSS while the sweep ran (``VmHWM`` of the ``gdwm sweep`` process when it prints ``sweep:``);
- ``gdwm compare`` of the sweep, ``gdwm status`` and ``gdwm cache ls`` (each a new process: what a user waits for);
- the dashboard's sweep page (``gdwm ui``): from the command to the sweep's table computed, then the page's GET.

Goals (issue 33): per-trial cost <= 0.5 s and flat (200 trials' <= 1.2x 10 trials'), RSS growing no faster than the
trials, compare <= 10 s for 200 rows. Run ``python -m benchmarks scale`` (``--quick``: 1, 4 and 8 trials); it prints
the table the README shows. PostgreSQL missing: the server side is skipped, said in the output.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from benchmarks.bench_ui import _median_get, _stop, gdwm_ui
from benchmarks.common import Result
from gdwm.term import console

CONF = Path(__file__).resolve().parent / "conf"
SIZES = (10, 50, 200)
QUICK_SIZES = (4, 8)


def _sweep_yaml(n: int) -> str:
    xs = ", ".join(f'"{i}"' for i in range(n))
    return f"""defaults:
  - /schema/sweep/sweep@_here_
  - _self_

name: noop_{n}
layout: nuinteract
overrides: [pipeline=noop_sweep, "+stage.prep={{}}", "+stage.fit.x=0", "+stage.score={{}}"]
grid:
  stage.fit.x: [{xs}]
"""


def _hwm_mb(pid: int) -> float:
    """The peak resident memory of a process so far (``VmHWM``), MB."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def _gdwm(args: list[str], env: dict) -> float:
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "gdwm", *args], env=env, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"gdwm {' '.join(args)} exited {r.returncode}:\n{r.stderr[-3000:]}")
    return time.perf_counter() - t0


def _sweep(n: int, args: list[str], env: dict) -> dict:
    """One sweep: the seconds it reports for its trials, its wall time, the driver's peak RSS during the sweep."""
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "gdwm", "sweep", f"sweep=noop_{n}", *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
    err: list[str] = []
    threading.Thread(target=lambda: err.extend(proc.stderr), daemon=True).start()
    reported, rss = None, float("nan")
    for line in proc.stdout:
        if m := re.match(r"^sweep: .* (\d+) s$", line.strip()):
            reported, rss = float(m.group(1)), _hwm_mb(proc.pid)
    proc.wait()
    if proc.returncode != 0 or reported is None:
        raise RuntimeError(f"gdwm sweep noop_{n} exited {proc.returncode}:\n{''.join(err)[-3000:]}")
    return {"trials_s": reported, "wall_s": time.perf_counter() - t0, "rss_mb": rss}


def _ui(args: list[str], env: dict) -> tuple[float, float]:
    """Seconds from ``gdwm ui`` to the newest sweep's table computed; median GET of that sweep's page."""
    t0 = time.perf_counter()
    workdir = next(a.split("=", 1)[1] for a in args if a.startswith("workdir="))
    g = gdwm_ui(Path(workdir), True, tuple(a for a in args if not a.startswith("workdir=")), env)
    try:
        ready = time.perf_counter() - t0
        page, _ = _median_get(f"{g['base']}/sweeps/{g['sweep']}", 3)
    finally:
        _stop(g["proc"])
    return ready, page


def measure(store: str, sizes: tuple[int, ...], base_env: dict, store_args: list[str], tmp: Path) -> list[dict]:
    rows = []
    for n in (1, *sizes):
        work = tmp / f"{store}-{n}"
        args = [f"workdir={work}", f"data.root={tmp / 'ds'}", "run.live=false", *store_args]
        sw = _sweep(n, args, base_env)
        row = {"store": store, "trials": n, **sw}
        if n > 1:
            row["compare_s"] = _gdwm(["compare", f"args.sweep=noop_{n}", *args[:1], *store_args,
                                      f"args.out={tmp / f'report-{store}-{n}'}"], base_env)  # fmt: skip
            row["status_s"] = _gdwm(["status", *args[:1], *store_args], base_env)
            row["cache_ls_s"] = _gdwm(["cache", "ls", *args[:1]], base_env)
            row["ui_ready_s"], row["ui_page_s"] = _ui([*args[:1], *store_args], base_env)
        shown = {k: round(v, 2) for k, v in row.items() if isinstance(v, float)}
        console.print(f"  {store} {n:>4} trials: {json.dumps(shown)}", markup=False)
        rows.append(row)
    one = rows[0]["trials_s"]
    for r in rows[1:]:
        r["per_trial_s"] = (r["trials_s"] - one) / (r["trials"] - 1)
    return rows


def table(rows: list[dict]) -> str:
    """The README's markdown table."""
    head = ("| store | trials | sweep s | per trial s | driver peak RSS MB | compare s | status s | cache ls s | "
            "ui: table ready s | ui: sweep page s |\n|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|")  # fmt: skip
    lines = [head]
    for r in rows:
        if r["trials"] == 1:
            lines.append(f"| {r['store']} | 1 | {r['trials_s']:.0f} | (fixed cost) | {r['rss_mb']:.0f} | | | | | |")
            continue
        lines.append(f"| {r['store']} | {r['trials']} | {r['trials_s']:.0f} | {r['per_trial_s']:.2f} | "
                     f"{r['rss_mb']:.0f} | {r['compare_s']:.1f} | {r['status_s']:.1f} | {r['cache_ls_s']:.1f} | "
                     f"{r['ui_ready_s']:.1f} | {r['ui_page_s']:.2f} |")  # fmt: skip
    return "\n".join(lines)


def run(quick: bool = False) -> list[Result]:
    from tests.gdwm.servers import pg_bindir, team_store
    from tests.gdwm.toydata import make_dataset

    sizes = QUICK_SIZES if quick else SIZES
    load = os.getloadavg()
    rows: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="gdwm-bench-scale-") as d:
        tmp = Path(d)
        make_dataset(tmp / "ds", scenes=1)
        (tmp / "conf" / "sweep").mkdir(parents=True)
        for n in (1, *sizes):
            (tmp / "conf" / "sweep" / f"noop_{n}.yaml").write_text(_sweep_yaml(n))
        repo = str(Path(__file__).resolve().parents[1])
        env = {**os.environ, "GDWM_CONF_PATH": os.pathsep.join([str(CONF), str(tmp / "conf")]),
               "PYTHONPATH": os.pathsep.join([repo, os.environ.get("PYTHONPATH", "")])}  # fmt: skip
        env = {k: v for k, v in env.items() if not k.startswith("MLFLOW_TRACKING_")}
        rows += measure("sqlite", sizes, env, [], tmp)
        if pg_bindir() is None:
            console.print("scale: PostgreSQL is not installed (make setup installs it): no server side", markup=False)
        else:
            (tmp / "team").mkdir()
            with team_store(tmp / "team", durable=True) as team:
                rows += measure("server", sizes, {**env, **team.server.creds()}, ["tracking=server"], tmp)
    md = table(rows)
    console.print(md, markup=False, highlight=False)
    detail = f"load average {load[0]:.1f}/{load[1]:.1f}/{load[2]:.1f} at the start on {os.cpu_count()} CPUs"
    out = []
    small, big = sizes[0], sizes[-1]
    for store in dict.fromkeys(r["store"] for r in rows):
        mine = {r["trials"]: r for r in rows if r["store"] == store}
        for n in sizes:
            out.append(Result("scale", f"{store}: per-trial cost, {n} trials", mine[n]["per_trial_s"], "s", 0.5,
                              detail=f"(T({n}) - T(1)) / {n - 1}; {detail}"))  # fmt: skip
        out.append(Result("scale", f"{store}: per-trial cost {big} / {small} trials",
                          mine[big]["per_trial_s"] / mine[small]["per_trial_s"], "x", 1.2))  # fmt: skip
        rss = mine[big]["rss_mb"] / mine[small]["rss_mb"]
        out.append(Result("scale", f"{store}: driver peak RSS {big} / {small} trials", rss, "x", big / small,
                          detail=f"{mine[small]['rss_mb']:.0f} -> {mine[big]['rss_mb']:.0f} MB"))  # fmt: skip
        out.append(Result("scale", f"{store}: gdwm compare, {big} rows", mine[big]["compare_s"], "s", 10.0))
        out.append(Result("scale", f"{store}: gdwm status, {big}-trial sweep", mine[big]["status_s"], "s"))
        out.append(Result("scale", f"{store}: gdwm cache ls, {big}-trial sweep", mine[big]["cache_ls_s"], "s"))
        out.append(Result("scale", f"{store}: ui sweep page, {big} trials", mine[big]["ui_page_s"], "s", 1.0,
                          detail=f"table ready {mine[big]['ui_ready_s']:.1f} s after the command"))  # fmt: skip
    return out
