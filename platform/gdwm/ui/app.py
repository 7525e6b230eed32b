"""The dashboard's web app: Starlette routes rendering Jinja2 templates, JSON for the parts a page refreshes.

Pages: ``/`` (launches), ``/sweeps/<run>`` (live grid, table, plots, downloads), ``/trials/<run>`` and
``/runs/<run>``, ``/regressions``, ``/zoo``. A live page asks ``/api/...`` every ``ui.poll_s`` seconds and replaces
its fragments in place (no reload). A read that fails (the store went away, a server refused) gives a page that
says which store and why, with status 503.
"""

from __future__ import annotations

import hashlib
import shutil
import tempfile
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path
from typing import Any

from jinja2 import Environment, FileSystemLoader, select_autoescape
from starlette.applications import Starlette
from starlette.background import BackgroundTask
from starlette.concurrency import run_in_threadpool
from starlette.middleware import Middleware
from starlette.middleware.gzip import GZipMiddleware
from starlette.requests import Request
from starlette.responses import FileResponse, HTMLResponse, JSONResponse, PlainTextResponse, RedirectResponse, Response
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles

from gdwm.progress import duration
from gdwm.ui import pages
from gdwm.ui.pages import Context
from gdwm.ui.store import StoreError

HERE = Path(__file__).parent
STATE_CLASS = {
    "running": "running",
    "stale": "stale",
    "done": "done",
    "failed": "failed",
    "killed": "killed",
    "pending": "pending",
    "cached": "cached",
    "shared": "shared",
    "blocked": "blocked",
}


def plotly_js() -> Path:
    import plotly

    return Path(plotly.__file__).parent / "package_data" / "plotly.min.js"


def _env() -> Environment:
    env = Environment(loader=FileSystemLoader(HERE / "templates"), autoescape=select_autoescape(["html"]))
    env.filters["duration"] = lambda s: duration(s) if isinstance(s, int | float) else ""
    env.filters["short"] = lambda s, n=12: (s or "")[:n]
    env.globals["STATE_CLASS"] = STATE_CLASS
    return env


def create_app(ctx: Context, auth: Any = None) -> Starlette:
    env = _env()

    def page(name: str, status: int = 200, **data: Any) -> HTMLResponse:
        data.setdefault("store", ctx.store.shown)
        data.setdefault("poll_s", ctx.poll_s)
        return HTMLResponse(env.get_template(name).render(ctx=ctx, **data), status_code=status)

    def guarded(fn):
        async def endpoint(request: Request) -> Response:
            try:
                return await run_in_threadpool(fn, request)
            except StoreError as e:
                if request.url.path.startswith("/api/"):
                    return JSONResponse({"error": str(e)}, status_code=503)
                return page("error.html", 503, title="store unreachable", message=str(e))

        return endpoint

    def home(request: Request) -> Response:
        q, state = request.query_params.get("q", ""), request.query_params.get("state", "")
        lists = pages.launches(ctx, q, state)
        return page("home.html", lists=lists, q=q, state=state, states=pages.STATES, title="gdwm")

    def home_api(request: Request) -> Response:
        q, state = request.query_params.get("q", ""), request.query_params.get("state", "")
        lists = pages.launches(ctx, q, state)
        return JSONResponse({"html": env.get_template("_launches.html").render(ctx=ctx, lists=lists)})

    def _sweep(request: Request) -> pages.Sweep:
        run = ctx.store.run(request.path_params["run_id"])
        return pages.load_sweep(ctx, run)

    def sweep_fragments(sweep: pages.Sweep) -> dict[str, Any]:
        live = pages.sweep_live(ctx, sweep)
        entry = pages.want_table(ctx, sweep)
        snap = live.snapshot
        c = snap.get("counts", {})
        data = {
            "sweep": sweep,
            "live": live,
            "snap": snap,
            "counts": c,
            "entry": entry,
            "hrefs": sweep.trial_href(),
            "mlflow": ctx.mlflow_run(sweep.run),
            "took": pages.took(sweep.run),
            "started": pages.when(sweep.run["start_time"]),
        }
        finished = live.state != "running"
        over = (
            entry is None
            or entry.state == "failed"
            or (entry.current and entry.effects is not None and entry.report is not None)
        )
        return {
            "data": data,
            "state": live.state,
            "done": c.get("trials_done", 0),
            "failed": c.get("trials_failed", 0),
            "total": c.get("trials", 0),
            "finished": finished,
            "settled": finished and over,
            "table_version": entry.version if entry is not None else 0,
        }

    def sweep_page(request: Request) -> Response:
        run = ctx.store.run(request.path_params["run_id"])
        if run["tags"].get("gdwm.kind") != "sweep":
            return RedirectResponse(f"/runs/{run['run_id']}")
        f = sweep_fragments(pages.load_sweep(ctx, run))
        return page("sweep.html", title=f"sweep {f['data']['sweep'].name}", **f["data"], frag=f)

    def sweep_live_api(request: Request) -> Response:
        f = sweep_fragments(_sweep(request))
        d = f.pop("data")
        out = {k: v for k, v in f.items()}
        out["head"] = env.get_template("_sweep_head.html").render(ctx=ctx, **d)
        out["grid"] = env.get_template("_grid.html").render(ctx=ctx, **d)
        out["table"] = env.get_template("_table.html").render(ctx=ctx, **d)
        return JSONResponse(out)

    def sweep_charts(request: Request) -> Response:
        from gdwm.ui import charts

        sweep = _sweep(request)
        entry = ctx.tables.get(sweep.run["run_id"])
        if entry is None or entry.table is None:  # the curves need no table
            return JSONResponse({"ready": False, "stages": _curve_stages(sweep)})
        t = entry.table
        out = {
            "ready": True,
            "version": entry.version,
            "values": charts.values(t),
            "parallel": charts.parallel(t),
            "effects": charts.effects(entry.effects or [], t.get("key_metric")),
            "effects_ready": entry.effects is not None,
            "stages": _curve_stages(sweep),
        }
        return JSONResponse(out)

    def _curve_stages(sweep: pages.Sweep) -> list[str]:
        names = {r["tags"]["gdwm.stage"] for r in sweep.stage_runs.values()}
        used = {
            k.removeprefix("gdwm.stage_run.")
            for t in sweep.trials
            for k in t["tags"]
            if k.startswith("gdwm.stage_run.")
        }
        order = {
            s: min((r["start_time"] or 0) for r in sweep.stage_runs.values() if r["tags"]["gdwm.stage"] == s)
            for s in names
        }
        stages = sorted(names & used if used else names, key=order.__getitem__)
        # stages that logged a loss first: the select opens on a training curve
        trained = {r["tags"]["gdwm.stage"] for r in sweep.stage_runs.values() if any("loss" in k for k in r["metrics"])}
        return [s for s in stages if s in trained] + [s for s in stages if s not in trained]

    def sweep_curves(request: Request) -> Response:
        from gdwm.ui import charts

        sweep = _sweep(request)
        stage = request.query_params.get("stage", "")
        rows: dict[str, dict[str, list]] = {}
        row_label = {r["run_id"]: r["tags"].get("gdwm.row", r["name"]) for r in sweep.rows}
        for t in sweep.trials:
            rid = t["tags"].get(f"gdwm.stage_run.{stage}")
            srun = sweep.stage_runs.get(rid) if rid else None
            if srun is None:
                continue
            label = row_label.get(t["tags"].get("mlflow.parentRunId"), t["tags"].get("gdwm.row", t["name"]))
            finished = srun["status"] in pages.TERMINAL
            for key in sorted(srun["metrics"]):
                if key.startswith("system/"):
                    continue
                h = ctx.store.history(srun["run_id"], key, finished)
                if len({s for s, _ in h}) > 1:
                    rows.setdefault(label, {}).setdefault(key, []).append(h)
        return JSONResponse({"stage": stage, "figure": charts.curves(stage, rows)})

    def download(request: Request) -> Response:
        sweep = _sweep(request)
        fmt = request.path_params["fmt"]
        entry = pages.want_table(ctx, sweep)  # asked for before its page was opened: computed now
        layout = sweep.config.get("layout") or "table"
        if entry is None or entry.table is None or (fmt == "html" and entry.report is None):
            msg = "being computed" if entry is not None and entry.state != "failed" else "not available"
            return PlainTextResponse(
                f"the {fmt} of sweep {sweep.name} is {msg}; try again in a minute",
                status_code=503,
                headers={"Retry-After": "30"},
            )
        body, media = {
            "md": (entry.table["markdown"], "text/markdown"),
            "tex": (entry.table["latex"], "application/x-tex"),
            "csv": (entry.table["csv"], "text/csv"),
            "html": (entry.report, "text/html"),
        }[fmt]
        name = f"{sweep.name}-{layout}.{fmt}"
        return Response(
            body,
            media_type=f"{media}; charset=utf-8",
            headers={"Content-Disposition": f'attachment; filename="{name}"'},
        )

    def trial(request: Request) -> Response:
        data = pages.trial_page(ctx, request.path_params["run_id"])
        return page("trial.html", title=f"trial {data['label']}", **data)

    def run_page(request: Request) -> Response:
        run = ctx.store.run(request.path_params["run_id"])
        kind = run["tags"].get("gdwm.kind")
        if kind == "sweep":
            return RedirectResponse(f"/sweeps/{run['run_id']}")
        if kind == "regression":
            return RedirectResponse(f"/regressions?benchmark={run['tags'].get('gdwm.benchmark', '')}")
        data = pages.trial_page(ctx, run["run_id"])
        seeds = ctx.store.search(f"tags.`mlflow.parentRunId` = '{run['run_id']}' and tags.`gdwm.kind` = 'trial'")
        return page("trial.html", title=f"run {run['name']}", seeds=seeds, **data)

    def why(request: Request) -> Response:
        """Why the trial's stages that ran did (asked of the cache once per trial, in a worker)."""
        run_id = request.path_params["run_id"]
        if ctx.whys is None:
            return JSONResponse({"ready": True, "why": {}, "error": "no cache configured"})
        hit = ctx.whys.get(run_id)
        if not hit["ready"] and not hit["why"] and run_id not in ctx.whys.found:
            data = pages.trial_page(ctx, run_id)
            ran = [(s.stage, s.run["run_id"]) for s in data["stages"] if s.state in ("done", "failed") and s.run]
            hit = ctx.whys.get(run_id, ran) if ran else {"ready": True, "why": {}}
        return JSONResponse(hit)

    def regressions(request: Request) -> Response:
        from gdwm.ui import charts

        bench = request.query_params.get("benchmark") or None
        found = pages.regressions(ctx, bench)
        figures = {}
        for name, runs in found.items():
            metrics = list(dict.fromkeys(c["metric"] for r in runs for c in r["checks"]))
            for m in metrics:
                points = []
                for r in runs:
                    c = next((c for c in r["checks"] if c["metric"] == m), None)
                    value = c.get("now") if c else r["run"]["metrics"].get(m)
                    if value is None:
                        continue
                    points.append(
                        {
                            "date": r["date"],
                            "commit": r["commit"],
                            "digest": r["digest"],
                            "value": value,
                            "verdict": c["verdict"] if c else r["verdict"],
                            "baseline": c.get("baseline") if c else None,
                            "allowed": c.get("allowed") if c else None,
                            "direction": (c or {}).get("direction", "higher"),
                            "tolerance": (c or {}).get("tolerance", ""),
                            "is_baseline": r["baseline"],
                        }
                    )
                figures[f"{name}::{m}"] = charts.trend(m, points)
        return page("regressions.html", title="regressions", found=found, figures=figures, benchmark=bench)

    def zoo(request: Request) -> Response:
        return page("zoo.html", title="model zoo", versions=pages.zoo(ctx))

    def artifact(request: Request) -> Response:
        run_id, path = request.path_params["run_id"], request.path_params["path"]
        if ".." in Path(path).parts or path.startswith("/"):
            return PlainTextResponse(f"artifact path {path!r}: not inside the run", status_code=400)
        if not ctx.store.exists(run_id, path):
            return PlainTextResponse(f"run {run_id} has no artifact {path}", status_code=404)
        tmp = tempfile.mkdtemp(prefix="gdwm-ui-artifact-")
        local = ctx.store.download(run_id, path, tmp)
        return FileResponse(
            local, filename=Path(path).name, background=BackgroundTask(shutil.rmtree, tmp, ignore_errors=True)
        )

    def health(_request: Request) -> Response:
        return PlainTextResponse("OK")

    routes = [
        Route("/", guarded(home)),
        Route("/health", health),
        Route("/api/launches", guarded(home_api)),
        Route("/sweeps/{run_id}", guarded(sweep_page)),
        Route("/sweeps/{run_id}/download/{fmt:str}", guarded(download)),
        Route("/api/sweeps/{run_id}/live", guarded(sweep_live_api)),
        Route("/api/sweeps/{run_id}/charts", guarded(sweep_charts)),
        Route("/api/sweeps/{run_id}/curves", guarded(sweep_curves)),
        Route("/trials/{run_id}", guarded(trial)),
        Route("/api/trials/{run_id}/why", guarded(why)),
        Route("/runs/{run_id}", guarded(run_page)),
        Route("/regressions", guarded(regressions)),
        Route("/zoo", guarded(zoo)),
        Route("/artifacts/{run_id}/{path:path}", guarded(artifact)),
        Mount("/static/plotly", app=StaticFiles(directory=plotly_js().parent), name="plotly"),
        Mount("/static", app=StaticFiles(directory=HERE / "static"), name="static"),
    ]
    middleware = [Middleware(GZipMiddleware, minimum_size=1000)]
    if auth is not None:
        middleware.insert(0, Middleware(BasicAuth, check=auth))
    return Starlette(routes=routes, middleware=middleware)


class BasicAuth:
    """Every request needs HTTP basic-auth credentials that ``check`` accepts (``MlflowAuth``); ``/health`` is open
    (the probes)."""

    def __init__(self, app, check):
        self.app, self.check = app, check

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["path"] == "/health":
            return await self.app(scope, receive, send)
        header = dict(scope["headers"]).get(b"authorization", b"").decode("latin-1")
        if header.startswith("Basic ") and await run_in_threadpool(self.check, header):
            return await self.app(scope, receive, send)
        response = PlainTextResponse(
            "gdwm dashboard: log in with your MLflow user",
            status_code=401,
            headers={"WWW-Authenticate": 'Basic realm="gdwm"'},
        )
        return await response(scope, receive, send)


class MlflowAuth:
    """Credentials are good when the tracking server accepts them for the experiment (200 on
    ``experiments/get-by-name``): the dashboard's users and passwords are the MLflow server's. Answers are kept for
    ``ttl_s`` by a hash of the header (never the password itself)."""

    def __init__(self, tracking_uri: str, experiment: str, ttl_s: float = 60.0):
        self.url = f"{tracking_uri.rstrip('/')}/api/2.0/mlflow/experiments/get-by-name?" + urllib.parse.urlencode(
            {"experiment_name": experiment}
        )
        self.ttl_s = ttl_s
        self._seen: dict[str, tuple[float, bool]] = {}
        self._lock = threading.Lock()

    def __call__(self, header: str) -> bool:
        digest = hashlib.sha256(header.encode()).hexdigest()
        now = time.monotonic()
        hit = self._seen.get(digest)
        if hit is not None and now - hit[0] < self.ttl_s:
            return hit[1]
        req = urllib.request.Request(self.url, headers={"Authorization": header})
        try:
            with urllib.request.urlopen(req, timeout=20) as r:
                ok = r.status == 200
        except urllib.error.HTTPError as e:
            ok = e.code == 404  # the experiment does not exist yet, but the credentials were good
        except OSError:
            ok = False
        with self._lock:
            self._seen[digest] = (now, ok)
        return ok
