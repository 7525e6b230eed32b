"""A team's store, for real: ``tracking=server`` against MLflow with basic-auth on PostgreSQL, artifacts on S3 (moto),
the servers started once per session on loopback (``team`` in conftest.py; PostgreSQL as the unprivileged user
``postgres`` when the tests run as root). Drivers are the real CLI, each with its own local Ray, on the light
pipeline (tests/gdwm/light_stages.py: three file-writing stages a trial).

- four ``gdwm sweep``s from four workdirs at once, three on one cache on S3 and one on its own disk cache: every run
  once and FINISHED, every row's number the light pipeline's for that row;
- ``gdwm compare`` and the dashboard read the server, and agree cell for cell;
- a driver killed mid-sweep: the next launch reconciles what it left RUNNING and finishes the sweep;
- the store going down mid-sweep (its PostgreSQL stopped): the stage fails in one line naming the tracking URI, the
  cache keeps what was computed, the next launch continues; a PostgreSQL URI that refuses: exit 1 naming it;
- what one more trial asks of the server, request by request (the cost per trial the scale benchmark measures).
"""

from __future__ import annotations

import base64
import os
import re
import signal
import subprocess
import sys
import time
import urllib.request
from collections import Counter
from pathlib import Path

import mlflow
import pytest

from tests.gdwm.light_stages import light_value
from tests.gdwm.servers import TeamStore
from tests.gdwm.toydata import make_dataset

pytestmark = pytest.mark.heavy(3.5)

REPO = Path(__file__).resolve().parents[2]
ROWS = {"team_a": (1, 2), "team_b": (2, 3), "team_c": (4, 5)}
"""Each test sweep's rows: the value of ``stage.light_fit.x`` (tests/conf/sweep/team_*.yaml)."""
WAIT_S = 600


class Driver:
    """One user's workdir on the team store: ``gdwm sweep`` runs from it, its stages log what they executed."""

    def __init__(self, root: Path, team: TeamStore, data: Path, cache: str | None = None):
        self.root, self.team, self.data, self.cache = root, team, data, cache
        root.mkdir(parents=True, exist_ok=True)

    def env(self, **extra: str) -> dict[str, str]:
        keep = {k: v for k, v in os.environ.items()
                if not k.startswith(("GDWM_TEST_", "MLFLOW_", "AWS_")) and k != "RAY_AUTH_MODE"}  # fmt: skip
        return keep | self.team.s3.env() | self.team.server.creds() | {
            "PYTHONPATH": str(REPO), "GDWM_CONF_PATH": str(REPO / "tests" / "conf"), "GDWM_TEST_DIR": str(self.root),
        } | extra  # fmt: skip

    def args(self, sweep: str, *overrides: str) -> list[str]:
        cache = [f"cache.uri={self.cache}"] if self.cache else []
        where = [f"workdir={self.root / 'w'}", f"data.root={self.data}", "run.live=false", *cache]
        return [sys.executable, "-m", "gdwm", "sweep", f"sweep={sweep}", "tracking=server", *where, *overrides]

    def start(self, sweep: str, *overrides: str, **extra: str) -> subprocess.Popen:
        return subprocess.Popen(self.args(sweep, *overrides), env=self.env(**extra), stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True, start_new_session=True)  # fmt: skip

    def sweep(self, sweep: str, *overrides: str, **extra: str) -> subprocess.CompletedProcess:
        return subprocess.run(self.args(sweep, *overrides), env=self.env(**extra), capture_output=True, text=True,
                              timeout=WAIT_S)  # fmt: skip

    def executions(self) -> list[tuple[str, str]]:
        """(stage, key[:12]) of every execution this driver's stages ran."""
        log = self.root / "executions.log"
        return [tuple(x.split()[0:3:2]) for x in log.read_text().splitlines()] if log.exists() else []


def _done(p: subprocess.Popen) -> subprocess.CompletedProcess:
    out, err = p.communicate(timeout=WAIT_S)
    return subprocess.CompletedProcess(p.args, p.returncode, out, err)


def _ok(r: subprocess.CompletedProcess) -> None:
    assert r.returncode == 0, f"exit {r.returncode}\nSTDOUT\n{r.stdout[-3000:]}\nSTDERR\n{r.stderr[-5000:]}"


def _runs(team: TeamStore, *where: str) -> list:
    """Every run of the experiment ``gdwm`` matching the filters, read as the admin."""
    for k, v in team.server.creds("admin").items():
        os.environ[k] = v
    try:
        client = mlflow.MlflowClient(team.server.uri)
        exp = client.get_experiment_by_name("gdwm")
        return [] if exp is None else client.search_runs([exp.experiment_id], " and ".join(where), max_results=5000)
    finally:
        for k in team.server.creds():
            os.environ.pop(k, None)


def _of(runs: list, kind: str, sweep: str | None = None) -> list:
    return [r for r in runs if r.data.tags.get("gdwm.kind") == kind and sweep in (None, r.data.tags.get("gdwm.sweep"))]


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("light-data") / "ds", scenes=1)


@pytest.fixture(scope="module")
def four(team, data, tmp_path_factory) -> dict[str, Driver]:
    """Four drivers at once on the team store: two run team_a (the second waits on the launch's lock, then finds it
    all cached), one team_b (its row x 2 is team_a's) on the same S3 cache, one team_c on a disk cache of its own."""
    root = tmp_path_factory.mktemp("four")
    shared = "s3://gdwm/team-cache"
    drivers = {"a1": Driver(root / "a1", team, data, shared), "a2": Driver(root / "a2", team, data, shared),
               "b": Driver(root / "b", team, data, shared), "c": Driver(root / "c", team, data)}  # fmt: skip
    sweeps = {"a1": "team_a", "a2": "team_a", "b": "team_b", "c": "team_c"}
    procs = {name: d.start(sweeps[name]) for name, d in drivers.items()}
    for name, p in procs.items():
        drivers[name].result = _done(p)
    return drivers


def test_four_drivers_on_one_team_store(team, four):
    for d in four.values():
        _ok(d.result)
    runs = _runs(team)
    # every run once: a sweep run per sweep (team_a's second driver continued the first one's), a row and a trial run
    # per row, and a stage run per execution
    assert sorted(r.data.tags["gdwm.sweep"] for r in _of(runs, "sweep")) == ["team_a", "team_b", "team_c"]
    for sweep, xs in ROWS.items():
        for kind in ("row", "trial"):
            assert sorted(r.data.tags["gdwm.row"] for r in _of(runs, kind, sweep)) == [f"x {x}" for x in xs], kind
        trials = {r.data.tags["gdwm.row"]: r for r in _of(runs, "trial", sweep)}
        # every row's number is the light pipeline's for its x: what the same sweep gives alone
        assert {k: t.data.metrics["acc"] for k, t in trials.items()} == {f"x {x}": light_value(x, 0) for x in xs}
        # and links the stage runs it used
        stage_ids = {r.info.run_id for r in _of(runs, "stage")}
        assert all(t.data.tags[f"gdwm.stage_run.{s}"] in stage_ids for t in trials.values() for s in ("fit", "score"))
    assert {r.info.status for r in runs} == {"FINISHED"}
    executed = Counter(e for d in four.values() for e in d.executions())
    assert Counter((r.data.tags["gdwm.stage"], r.data.tags["gdwm.cache_key"][:12]) for r in _of(runs, "stage")) == (
        executed
    )
    # on the shared cache each key ran once, whichever driver got it: prep 1, fit and score 3 (x 1, 2, 3)
    shared = Counter(s for name in ("a1", "a2", "b") for s, _ in four[name].executions())
    assert shared == {"prep": 1, "fit": 3, "score": 3}
    assert four["a2"].executions() == [] or four["a1"].executions() == []  # one of team_a's drivers computed it
    assert sum("waiting for it to finish" in four[n].result.stdout for n in ("a1", "a2")) == 1
    assert Counter(s for s, _ in four["c"].executions()) == {"prep": 1, "fit": 2, "score": 2}  # its own cache
    # artifacts went through the server to S3
    assert any(k.endswith("/artifacts/cache_keys.json") for k in team.s3.objects("mlartifacts"))


def _get(url: str, auth: tuple[str, str]) -> tuple[int, str]:
    req = urllib.request.Request(url)
    req.add_header("Authorization", "Basic " + base64.b64encode(":".join(auth).encode()).decode())
    try:
        with urllib.request.urlopen(req, timeout=60) as r:
            return r.status, r.read().decode()
    except urllib.error.HTTPError as e:
        return e.code, e.read().decode()


def test_compare_and_the_dashboard_read_the_server(team, four, tmp_path):
    from tests.gdwm.ui.dash import dashboard

    d = four["b"]
    out = tmp_path / "report"
    c = subprocess.run([sys.executable, "-m", "gdwm", "compare", "args.sweep=team_b", "tracking=server",
                        f"workdir={d.root / 'w'}", f"args.out={out}", "args.formats=[csv]"], env=d.env(),
                       capture_output=True, text=True, timeout=WAIT_S)  # fmt: skip
    _ok(c)
    csv = (out / "nuinteract.csv").read_text()
    assert all(f",{light_value(x, 0)!r}," in csv for x in ROWS["team_b"]), csv  # the CSV's full-precision means
    trainer = ("trainer", team.server.trainer_password)
    env = {k: v for k, v in d.env().items() if k.startswith(("MLFLOW_", "AWS_"))}
    # as on k8s (ui.auth=mlflow): a request needs credentials the MLflow server accepts
    with dashboard("tracking=server", "ui.auth=mlflow", f"workdir={d.root / 'w'}", **env) as dash:
        status, page = _get(f"{dash.base}/", trainer)
        assert status == 200 and all(s in page for s in ROWS)  # every sweep on the server is listed
        sweep_id = next(r.info.run_id for r in _of(_runs(team), "sweep", "team_b"))
        deadline = time.monotonic() + WAIT_S
        while (got := _get(f"{dash.base}/sweeps/{sweep_id}/download/csv", trainer))[0] == 503:  # being computed
            assert time.monotonic() < deadline, got
            time.sleep(1)
        assert got == (200, csv)  # the dashboard's table is gdwm compare's, cell for cell
        assert _get(f"{dash.base}/", ("trainer", "wrong-password-1"))[0] == 401


def _wait_file(path: Path, proc: subprocess.Popen) -> None:
    deadline = time.monotonic() + WAIT_S
    while not path.exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            raise AssertionError(f"{path.name} never appeared: {proc.communicate()[1][-3000:]}")
        time.sleep(0.2)


def _requests(log: str) -> Counter:
    """The server's access log lines as ``(method, endpoint)``; artifacts by file name, the ids left out."""
    out: Counter = Counter()
    for m in re.finditer(r'"(GET|POST|PUT|DELETE) (/api/2\.0/[^ ?]+)', log):
        method, path = m.groups()
        if "/mlflow-artifacts/artifacts/" in path:
            path = "artifact " + re.sub(r"[0-9a-f]{12,}", "<id>", path.split("/artifacts/", 2)[-1])
        out[(method, path.removeprefix("/api/2.0/mlflow/"))] += 1
    return out


ORCHESTRATION = {
    ("POST", "runs/create"): 4,  # the row's run, the trial's, a stage run for each of fit and score
    ("POST", "runs/log-batch"): 6,  # params: the row's own, the trial's (its factor), each stage run's; the
    # trial's outcome, the row's aggregate
    ("POST", "runs/update"): 4,  # each of the four ends
    ("POST", "runs/search"): 2,  # each stage run's keyed search (a killed attempt's run is reopened, not duplicated)
    ("PUT", "artifact config.yaml"): 1,  # the trial's whole config
    ("PUT", "artifact cache_keys.json"): 1,  # the entries it is about to use (gc keeps them while it runs)
}
"""What gdwm asks of the team's server for one more trial (a new row, two stage executions): 18 requests."""
PER_TRIAL = ORCHESTRATION | {
    ("POST", "runs/log-batch"): 7,  # and the fit stage's own metric (tests/gdwm/light_stages.py)
    ("GET", "metrics/get-history"): 1,  # the sweep's report reads it (a training curve where it has steps)
}


def test_each_added_trial_costs_a_known_number_of_requests_to_the_store(team, data, tmp_path):
    """The cost per trial on a team's server is its requests (each ~20-40 ms on 2 cores): a sweep of 3 rows asks
    exactly 2 x ``PER_TRIAL`` more than one of 1 row (the scale benchmark's no-op trials: ``ORCHESTRATION``); a
    change that adds a request a trial fails here, by endpoint. Snapshots are written only at the start and end
    (``run.snapshot_s``), so nothing here depends on timing."""
    counts = []
    for n in (1, 3):
        before = team.server.log.read_text()
        _ok(Driver(tmp_path / f"n{n}", team, data).sweep(f"team_cost_{n}", "run.snapshot_s=100000"))
        counts.append(_requests(team.server.log.read_text()[len(before) :]))
    one, three = counts
    # the experiment is made by whichever launch comes first
    added = {k: (three[k] - one[k]) / 2 for k in one.keys() | three.keys() if three[k] != one[k]}
    assert {k: v for k, v in added.items() if not k[1].startswith("experiments/")} == PER_TRIAL


def test_a_killed_driver_leaves_no_running_run_once_the_next_launch_reconciles(team, data, tmp_path):
    d = Driver(tmp_path, team, data)
    proc = d.start("team_killed", GDWM_TEST_BLOCK="score")
    try:
        _wait_file(tmp_path / "blocked-score", proc)
        os.killpg(proc.pid, signal.SIGKILL)  # the driver and its local Ray: nothing ends its runs
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    left = {r.info.run_id: r for r in _runs(team, "tags.`gdwm.sweep` = 'team_killed'") if r.info.status == "RUNNING"}
    assert {r.data.tags["gdwm.kind"] for r in left.values()} >= {"sweep", "row", "trial", "stage"}
    _ok(d.sweep("team_killed"))
    runs = {r.info.run_id: r for r in _runs(team, "tags.`gdwm.sweep` = 'team_killed'")}
    assert {r.info.status for r in runs.values()} == {"FINISHED"}
    # what the killed driver left RUNNING was ended KILLED by the next launch's reconcile (which says so), then
    # continued: the same runs, no duplicates
    assert set(left) <= set(runs) and all("gdwm.reconciled" in runs[i].data.tags for i in left)
    assert len(_of(list(runs.values()), "sweep")) == 1 and len(_of(list(runs.values()), "trial")) == 2
    assert Counter(s for s, _ in d.executions())["prep"] == 1  # what the killed driver computed was kept


@pytest.mark.parametrize("why", ["wrong password", "nothing listens"])
def test_a_postgresql_store_that_refuses_exits_1_naming_it(team, data, tmp_path, why):
    good = team.backend_url
    user_pw = good.split("//", 1)[1].split("@", 1)[0]
    bad = good.replace(user_pw, "mlflow:wrong-password-1") if why == "wrong password" else (
        good.replace(f":{team.pg.port}/", ":1/"))  # fmt: skip
    d = Driver(tmp_path, team, data)
    t0 = time.monotonic()
    r = d.sweep("team_a", MLFLOW_TRACKING_URI=bad)
    assert r.returncode == 1, r.stderr[-3000:]
    shown = bad.replace(bad.split("//", 1)[1].split("@", 1)[0], "mlflow:***")
    cause = 'password authentication failed for user "mlflow"' if why == "wrong password" else "connection refused"
    (line,) = [x for x in r.stderr.splitlines() if x.strip()]
    assert line.startswith(f"gdwm sweep: TrackingError: tracking database {shown} refused the connection: ")
    assert cause in line and "wrong-password-1" not in r.stdout + r.stderr and user_pw not in r.stdout + r.stderr
    assert time.monotonic() - t0 < 120  # at once, not after MLflow's ten retries
    assert not (tmp_path / "executions.log").exists()


def test_the_store_going_down_mid_sweep_fails_in_one_line_and_the_next_launch_continues(team, data, tmp_path):
    """PostgreSQL stops under the server while ``score`` runs: the stage fails in one line naming the tracking URI,
    the driver exits 1; what was computed stays in the cache, and the next launch (PostgreSQL back) finishes the
    sweep without computing it again. Runs last in this module: the store blinks."""
    d = Driver(tmp_path, team, data)
    quick = {"MLFLOW_HTTP_REQUEST_MAX_RETRIES": "1", "MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR": "1"}
    proc = d.start("team_down", GDWM_TEST_BLOCK="score", **quick)
    stopped = False
    try:
        _wait_file(tmp_path / "blocked-score", proc)
        team.pg.stop()
        stopped = True
        (tmp_path / "release").touch()
        r = _done(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
        if stopped:
            team.pg.start()
    assert r.returncode == 1, r.stdout[-3000:] + r.stderr[-3000:]
    uri = team.server.uri
    assert f"tracking store {uri} failed" in r.stdout + r.stderr
    failed = [x for x in (r.stdout + r.stderr).splitlines() if "stage 'score'" in x and "failed" in x]
    assert failed and all(f"TrackingError: tracking store {uri} failed" in x for x in failed), failed
    assert "Traceback" not in r.stderr and team.server.trainer_password not in r.stdout + r.stderr
    before = d.executions()
    assert Counter(s for s, _ in before)["score"] >= 1
    _ok(d.sweep("team_down"))
    after = d.executions()
    # what the first launch computed came from the cache: each (stage, key) executed once over both launches
    assert after[: len(before)] == before and len(set(after)) == len(after), after
    assert Counter(s for s, _ in after) == {"prep": 1, "fit": 2, "score": 2}
    runs = _runs(team, "tags.`gdwm.sweep` = 'team_down'")
    trials = {r.data.tags["gdwm.row"]: r for r in _of(runs, "trial")}
    assert {k: (t.info.status, t.data.metrics["acc"]) for k, t in trials.items()} == {
        "x 8": ("FINISHED", light_value(8, 0)), "x 9": ("FINISHED", light_value(9, 0))}  # fmt: skip
    assert "RUNNING" not in {r.info.status for r in runs}
