"""``gdwm ui`` beside ``mlflow ui`` on the same store, in one run:

- from the command to HTTP 200: for ``gdwm ui``, until it prints its URL (printed once the deep-linked sweep page
  answered 200); for ``mlflow ui``, until ``/`` answers 200 (median over repeats, each a new process);
- resident memory of the whole server (the process and its children, ``psutil``): steady, once the sweep's table is
  computed and its worker process gone, and at its peak while the worker computes (``gdwm ui``); ``mlflow ui``'s
  once it answers;
- a 200-trial sweep's page (50 rows x 4 seeds, 5 stages each, 260 params per run, as ``gdwm sweep`` logs them) once
  its table is computed: the HTML of ``/sweeps/<id>`` and its live fragments ``/api/sweeps/<id>/live``.

The demo's store is ``$GDWM_BENCH_UI_STORE`` (a ``make demo`` workdir; its ``mlflow.db`` and ``mlartifacts`` are
copied), else ``./gdwm-work``, else a demo-shaped store written here (5 rows, one seed, the NuInteract metrics).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

import psutil

from benchmarks.common import Result

NUINTERACT = [
    "rdp_bleu",
    "rdp_rouge_l",
    "rdp_cider",
    "vg2d_map",
    "vg2d_f1",
    "vg2d_miou",
    "vg3d_pr",
    "vg3d_map",
    "vg3d_f1",
    "plan_acc",
    "avg",
]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _tree_rss(pid: int) -> float:
    """MB resident of a process and its descendants."""
    try:
        p = psutil.Process(pid)
        procs = [p, *p.children(recursive=True)]
    except psutil.NoSuchProcess:
        return 0.0
    total = 0
    for q in procs:
        try:
            total += q.memory_info().rss
        except psutil.NoSuchProcess:
            continue
    return total / 2**20


def _get(url: str, timeout: float = 60) -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=timeout) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as e:
        return e.code, b""
    except OSError:
        return 0, b""


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(timeout=30)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            os.killpg(proc.pid, signal.SIGKILL)


def gdwm_ui(workdir: Path, wait_table: bool, args: tuple[str, ...] = (), env: dict | None = None) -> dict:
    """Start ``gdwm ui`` on the store (``args``: more overrides, e.g. ``tracking=server``; ``env``: its environment);
    seconds to its URL, RSS (steady after the table, peak while computing)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-m", "gdwm", "ui", f"workdir={workdir}", *args, "--port", "0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
        env=env,
    )
    url, lines = None, []
    try:
        for line in proc.stdout:
            lines.append(line)
            if line.startswith("gdwm ui: http"):
                url = line.split()[2]
                break
        seconds = time.perf_counter() - t0
        if url is None:
            raise RuntimeError(f"gdwm ui printed no URL: {''.join(lines)[-2000:]}")
        threading.Thread(target=lambda: [None for _ in proc.stdout], daemon=True).start()
        out = {"seconds": seconds, "url": url, "rss_at_url": _tree_rss(proc.pid), "rss_self": 0.0}
        if wait_table:
            base, sweep = url.split("/sweeps/")
            peak, deadline = 0.0, time.monotonic() + 1800
            while time.monotonic() < deadline:
                peak = max(peak, _tree_rss(proc.pid))
                status, body = _get(f"{base}/api/sweeps/{sweep}/live")
                if status == 200 and json.loads(body).get("settled") and not psutil.Process(proc.pid).children():
                    break
                time.sleep(0.5)
            time.sleep(1.0)
            out |= {"rss_peak": peak, "rss_steady": _tree_rss(proc.pid), "base": base, "sweep": sweep}
        out["rss_self"] = psutil.Process(proc.pid).memory_info().rss / 2**20
        out["proc"] = proc
        return out
    except BaseException:
        _stop(proc)
        raise


def mlflow_ui(workdir: Path) -> dict:
    port = _free_port()
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "mlflow",
            "ui",
            "--backend-store-uri",
            f"sqlite:///{workdir}/mlflow.db",
            "--port",
            str(port),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    try:
        while _get(f"http://127.0.0.1:{port}/", timeout=5)[0] != 200:
            if proc.poll() is not None or time.perf_counter() - t0 > 600:
                raise RuntimeError(f"mlflow ui did not answer (exit {proc.poll()})")
            time.sleep(0.1)
        seconds = time.perf_counter() - t0
        time.sleep(1.0)
        return {"seconds": seconds, "rss": _tree_rss(proc.pid)}
    finally:
        _stop(proc)


def _copy_store(src: Path, dst: Path) -> Path:
    dst.mkdir(parents=True)
    shutil.copy2(src / "mlflow.db", dst / "mlflow.db")
    if (src / "mlartifacts").is_dir():
        shutil.copytree(src / "mlartifacts", dst / "mlartifacts", symlinks=True)
    return dst


def write_sweep(workdir: Path, rows: int, seeds: int, params: int = 260, steps: int = 50) -> None:
    """A finished sweep as ``gdwm sweep`` logs it: rows x seeds trial runs with the NuInteract metrics, 5 stages each
    (reconstruct and distill shared by all, tokenizer per seed, lora and evaluate_qa per trial, lora with a loss
    curve), ``params`` params per row and trial, the progress snapshot."""
    import random

    from mlflow import MlflowClient
    from mlflow.entities import Metric, Param, RunTag

    client = MlflowClient(f"sqlite:///{workdir}/mlflow.db")
    exp = client.create_experiment(
        "gdwm", str(workdir / "mlartifacts"), tags={"mlflow.experimentKind": "custom_model_development"}
    )
    rng = random.Random(0)
    now = int(time.time() * 1000)

    def run(name: str, tags: dict, parent: str | None = None) -> str:
        tags = {**tags, **({"mlflow.parentRunId": parent} if parent else {})}
        return client.create_run(exp, run_name=name, tags=tags).info.run_id

    def batch(
        run_id: str, metrics: dict | None = None, params: dict | None = None, tags: dict | None = None, step: int = 0
    ) -> None:
        ms = [Metric(k, v, now, step) for k, v in (metrics or {}).items()]
        ps = [Param(k, v) for k, v in (params or {}).items()]
        for i in range(0, max(len(ps), 1), 100):
            client.log_batch(
                run_id,
                metrics=ms if i == 0 else [],
                params=ps[i : i + 100],
                tags=[RunTag(k, v) for k, v in (tags or {}).items()] if i == 0 else [],
            )

    sweep = run("sweep-bench", {"gdwm.kind": "sweep", "gdwm.sweep": "bench"})
    config = {f"stage.s{j}.p{k}": str(k) for j in range(params // 10) for k in range(10)}
    shared = {
        s: run(
            f"{s}-shared",
            {"gdwm.kind": "stage", "gdwm.stage": s, "gdwm.sweep": "bench", "gdwm.cache_key": f"{s}key"},
            sweep,
        )
        for s in ("reconstruct", "distill")
    }
    tokenizer = {}
    for seed in range(seeds):
        tokenizer[seed] = run(
            f"tokenizer-{seed}",
            {"gdwm.kind": "stage", "gdwm.stage": "tokenizer", "gdwm.sweep": "bench", "gdwm.cache_key": f"tok{seed}"},
            sweep,
        )
    for rid in [*shared.values(), *tokenizer.values()]:
        client.set_terminated(rid)
    snap_trials = {}
    for r in range(rows):
        factors = {"Rank": str(2 ** (r % 5)), "Selector": ("voxel", "driving")[r % 2], "Alignment": "✓✗"[r // 25 % 2]}
        label = f"row {r:02d}"
        common = {
            "gdwm.row": label,
            "gdwm.sweep": "bench",
            "gdwm.trial_index": str(r),
            "gdwm.seeds": ",".join(map(str, range(seeds))),
            **{f"gdwm.factor.{k}": v for k, v in factors.items()},
        }
        row = run(f"bench/{label}", {**common, "gdwm.kind": "row"}, sweep)
        batch(row, params=config)
        for seed in range(seeds):
            name = f"{label}, seed {seed}"
            lora = run(
                f"lora-{r}-{seed}",
                {"gdwm.kind": "stage", "gdwm.stage": "lora", "gdwm.sweep": "bench", "gdwm.cache_key": f"lora{r}{seed}"},
                sweep,
            )
            ms = [Metric("loss", 2.0 / (1 + s) + rng.random() * 0.1, now + s, s) for s in range(steps)]
            client.log_batch(lora, metrics=ms)
            ev = run(
                f"evaluate_qa-{r}-{seed}",
                {
                    "gdwm.kind": "stage",
                    "gdwm.stage": "evaluate_qa",
                    "gdwm.sweep": "bench",
                    "gdwm.cache_key": f"ev{r}{seed}",
                },
                sweep,
            )
            for rid in (lora, ev):
                client.set_terminated(rid)
            links = {
                "reconstruct": shared["reconstruct"],
                "distill": shared["distill"],
                "tokenizer": tokenizer[seed],
                "lora": lora,
                "evaluate_qa": ev,
            }
            trial = run(f"bench/{name}", {**common, "gdwm.kind": "trial", "gdwm.seed": str(seed)}, row)
            metrics = {f"nuinteract/{m}": 30 + 10 * rng.random() + r % 7 for m in NUINTERACT}
            batch(
                trial,
                metrics=metrics,
                params=config,
                tags={f"gdwm.stage_run.{s}": v for s, v in links.items()}
                | {f"gdwm.stage_key.{s}": f"{s}{r}{seed}" for s in links},
            )
            client.set_terminated(trial)
            snap_trials[name] = {
                "state": "done",
                "stages": {
                    s: {
                        "state": "done"
                        if s in ("lora", "evaluate_qa")
                        or (s == "tokenizer" and r == 0)
                        or (s in shared and r == 0 and seed == 0)
                        else "shared",
                        "key": f"{s}{r}{seed}",
                        "duration_s": 12.5,
                    }
                    for s in links
                },
            }
        client.set_terminated(row)
    n = rows * seeds
    snap = {
        "format": 1,
        "launch": "sweep-bench",
        "kind": "sweep",
        "name": "bench",
        "state": "done",
        "started": now / 1000,
        "updated": now / 1000 + 60,
        "elapsed_s": 60.0,
        "eta_s": None,
        "counts": {
            "executions": 3 * n,
            "executions_finished": 3 * n,
            "trials": n,
            "trials_done": n,
            "trials_failed": 0,
        },
        "summary": "",
        "events": None,
        "stages": ["reconstruct", "distill", "tokenizer", "lora", "evaluate_qa"],
        "trials": snap_trials,
        "failures": [],
    }
    client.log_text(sweep, json.dumps(snap), "progress/snapshot.json")
    client.log_text(sweep, "name: bench\nlayout: nuinteract\n", "sweep.yaml")
    batch(sweep, tags={"gdwm.trials_done": str(n), "gdwm.trials_failed": "0", "gdwm.trials_total": str(n)})
    client.set_terminated(sweep)


def _median_get(url: str, repeats: int) -> tuple[float, list[float]]:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        status, _ = _get(url)
        if status != 200:
            raise RuntimeError(f"{url}: HTTP {status}")
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times


def run(quick: bool = False) -> list[Result]:
    repeats = 1 if quick else 3
    load = os.getloadavg()[0]
    out: list[Result] = []
    with tempfile.TemporaryDirectory(prefix="gdwm-bench-ui-") as tmp:
        tmp = Path(tmp)
        src = os.environ.get("GDWM_BENCH_UI_STORE") or ("./gdwm-work" if Path("gdwm-work/mlflow.db").is_file() else "")
        if src:
            demo = _copy_store(Path(src).resolve(), tmp / "demo")
            what = f"a copy of {src}"
        else:
            demo = tmp / "demo"
            demo.mkdir()
            write_sweep(demo, rows=5, seeds=1)
            what = "a demo-shaped store (5 rows, 1 seed)"
        subprocess.run([sys.executable, "-m", "gdwm", "status", f"workdir={demo}"], capture_output=True)  # relocate
        g_times, m_times, first = [], [], None
        for k in range(repeats):
            g = gdwm_ui(demo, wait_table=k == 0)
            _stop(g.pop("proc"))
            first = first or g
            g_times.append(g["seconds"])
            m_times.append(mlflow_ui(demo)["seconds"])
        m_rss = mlflow_ui(demo)["rss"]
        g_med, m_med = statistics.median(g_times), statistics.median(m_times)
        detail = f"{what}; load average {load:.1f} on {os.cpu_count()} CPUs; runs {[f'{x:.1f}' for x in g_times]}"
        out.append(Result("ui", "gdwm ui: command -> deep link answered 200", g_med, "s", 3.0, detail=detail))
        out.append(
            Result(
                "ui",
                "mlflow ui: command -> / answered 200",
                m_med,
                "s",
                detail=f"same store; runs {[f'{x:.1f}' for x in m_times]}; ratio {m_med / g_med:.1f}x",
            )
        )
        out.append(
            Result(
                "ui",
                "gdwm ui RSS, whole server (table computed, worker gone)",
                first["rss_steady"],
                "MB",
                300.0,
                detail=f"at its URL {first['rss_at_url']:.0f} MB",
            )
        )
        out.append(
            Result(
                "ui",
                "gdwm ui RSS peak, with the table's worker process",
                first["rss_peak"],
                "MB",
                detail="transient: the bootstrap over held-out samples runs in a child process",
            )
        )
        out.append(Result("ui", "mlflow ui RSS, whole server", m_rss, "MB", detail="same store, after / answered"))
        big = tmp / "big"
        big.mkdir()
        t0 = time.perf_counter()
        rows, seeds = (10, 4) if quick else (50, 4)
        write_sweep(big, rows=rows, seeds=seeds)
        made = time.perf_counter() - t0
        g = gdwm_ui(big, wait_table=True)
        try:
            page, ts = _median_get(f"{g['base']}/sweeps/{g['sweep']}", 5)
            live, _ = _median_get(f"{g['base']}/api/sweeps/{g['sweep']}/live", 5)
        finally:
            _stop(g["proc"])
        n = rows * seeds
        out.append(
            Result(
                "ui",
                f"{n}-trial sweep page once its table is computed",
                page,
                "s",
                1.0,
                detail=f"median of 5 GETs {[f'{x:.2f}' for x in ts]}; store written in {made:.0f} s",
            )
        )
        out.append(Result("ui", f"{n}-trial sweep live fragments (what a page polls)", live, "s", 1.0))
    return out
