"""What a launch says, end to end through the CLI on local Ray with the toy stages: the sweep board redrawing in a
terminal (a pty read through pyte), a piped sweep's timestamped lines and heartbeats while a stage is held, a stage
whose setup raises (one cause, the traceback in a file, downstream blocked, setup run once per actor), MLflow rows a
comparison can filter on, and a copied workdir that leaves its original byte for byte."""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import pty
import re
import shutil
import struct
import subprocess
import sys
import termios
from pathlib import Path

import pyte
import pytest

from gdwm.events import read_events
from tests.gdwm.test_run import Toy, _ok

pytestmark = pytest.mark.heavy(2)

COLS, ROWS = 160, 60


def _gdwm(toy: Toy, *args: str) -> list[str]:
    return [sys.executable, "-m", "gdwm", *args, f"workdir={toy.work}", f"data.root={toy.data}"]


@pytest.fixture(scope="module")
def terminal_sweep(tmp_path_factory) -> tuple[Toy, list[str], str]:
    """The toy sweep run in a pseudo-terminal; every screen pyte drew from its output, in order."""
    toy = Toy(tmp_path_factory.mktemp("terminal"))
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", ROWS, COLS, 0, 0))
    env = toy.env(TERM="xterm", COLUMNS=str(COLS), LINES=str(ROWS))
    proc = subprocess.Popen(_gdwm(toy, "sweep", "sweep=toy_ablation"), stdin=slave, stdout=slave, stderr=slave,
                            env=env, close_fds=True)  # fmt: skip
    os.close(slave)
    screen, stream, screens, raw = pyte.Screen(COLS, ROWS), pyte.ByteStream(), [], b""
    stream.attach(screen)
    while True:
        try:
            chunk = os.read(master, 4096)  # blocks until the launch writes; EIO once it has exited
        except OSError:
            break
        if not chunk:
            break
        raw += chunk
        stream.feed(chunk)
        screens.append("\n".join(screen.display))
    os.close(master)
    assert proc.wait(timeout=60) == 0, raw.decode(errors="replace")[-3000:]
    (toy.root / "typescript.txt").write_bytes(raw)
    return toy, screens, raw.decode(errors="replace")


def test_the_board_redraws_with_trials_done_rising(terminal_sweep):
    _, screens, _ = terminal_sweep
    seen = []
    for s in screens:
        found = re.findall(r"trials (\d)/3 done", s)
        if found and (not seen or seen[-1] != found[-1]):
            seen.append(found[-1])
    assert seen[0] == "0" and seen[-1] == "3" and seen == sorted(seen) and len(seen) >= 3, seen
    last = screens[-1]
    assert re.search(r"│ rank 8 +│ done +│ shared +│ shared +│ shared +│ done +│ done +│", last), last


def test_factors_are_params_and_intervals_metrics(terminal_sweep):
    toy, _, _ = terminal_sweep
    exp = toy.client().get_experiment_by_name("gdwm")
    assert exp.tags["mlflow.experimentKind"] == "custom_model_development"  # MLflow's UI opens on the runs
    rows = toy.client().search_runs([exp.experiment_id], "params.`factor.Rank` = '8' and tags.`gdwm.kind` = 'row'")
    (row,) = rows
    m = row.data.metrics
    assert m["nuinteract/plan_acc"] == 96.0
    assert m["nuinteract/plan_acc/ci_low"] < 96.0 < m["nuinteract/plan_acc/ci_high"]
    assert not [k for k in m if k.startswith(("n/", "count/"))] and row.data.tags["gdwm.n.nuinteract/plan_acc"] == "1"
    (sweep,) = toy.runs("sweep")
    # the config the rows share is on the sweep's run (each row's params are what differs), paths relative
    params = sweep.data.params | row.data.params
    assert row.data.tags["gdwm.params_base"] == sweep.info.run_id
    assert not [v for v in params.values() if v.startswith("/") or "sqlite:////" in v]
    assert params["workdir"] == "." and params["cache.uri"] == "cache"
    assert "| rank 8 | 8 |" in sweep.data.tags["mlflow.note.content"]
    assert sweep.data.tags["gdwm.best_row"] == "rank 8" and sweep.data.tags["gdwm.key_metric"] == "nuinteract/plan_acc"
    snap = json.loads(Path(toy.client().download_artifacts(sweep.info.run_id, "progress/snapshot.json",
                                                           str(toy.root))).read_text())  # fmt: skip
    assert snap["state"] == "done" and snap["counts"]["trials_done"] == 3
    assert sweep.data.tags["gdwm.trials_done"] == "3" and sweep.data.tags["gdwm.state"] == "done"


def test_status_shows_the_sweep(terminal_sweep, capsys):
    from gdwm.cli import main

    toy, _, _ = terminal_sweep
    assert main(["status", f"workdir={toy.work}"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"│ toy_ablation │ done +│ 3/3 +│ .* │ rank 8 \(nuinteract/plan_acc 96\.00\) │", out), out


def _digest(root: Path) -> dict[str, str]:
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}  # fmt: skip


def test_a_copied_workdir_works_alone(terminal_sweep, tmp_path):
    toy, _, _ = terminal_sweep
    before = _digest(toy.work)
    copy = Toy(tmp_path)  # its own injection dir; the same dataset
    copy.data = toy.data
    shutil.copytree(toy.work, copy.work)
    r = subprocess.run(
        _gdwm(copy, "compare", "args.sweep=toy_ablation", "compare=nuinteract", "args.formats=[markdown]"),
        env=copy.env(),
        capture_output=True,
        text=True,
        timeout=300,
    )
    _ok(r)
    assert (copy.work / "reports" / "toy_ablation" / "nuinteract.md").is_file()
    r = subprocess.run(_gdwm(copy, "sweep", "sweep=toy_ablation", "--quiet"), env=copy.env(), capture_output=True,
                       text=True, timeout=600)  # fmt: skip
    _ok(r)
    assert not (tmp_path / "executions.log").exists()  # every stage cached
    (sweep,) = copy.runs("sweep")
    assert sweep.info.artifact_uri.startswith(copy.work.as_uri())
    assert _digest(toy.work) == before


def test_a_piped_sweep_logs_a_line_per_stage_and_heartbeats_while_held(tmp_path):
    toy = Toy(tmp_path)
    args = _gdwm(toy, "sweep", "sweep=toy_ablation", "sweep.only=[rank 4,rank 8]", "run.heartbeat_s=1")
    proc = subprocess.Popen(args, env=toy.env(GDWM_TEST_BLOCK="lora:step=1"), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)  # fmt: skip
    lines, beats = [], 0
    for line in proc.stdout:  # waits on the launch's own output, line by line
        lines.append(line.rstrip("\n"))
        if re.search(r"lora · rank \d: running .*step 2/3", line):
            beats += 1
            if beats == 2:
                (tmp_path / "release").touch()
    assert proc.wait(timeout=120) == 0, "\n".join(lines[-40:])
    stamp = r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d \[\d/7\]"
    assert [x for x in lines if re.match(rf"{stamp} tokenizer · rank 4, rank 8: done in .* \(shared by 2 trials\)"
                                         r" · trials 0/2", x)], lines  # fmt: skip
    assert len([x for x in lines if re.match(rf"{stamp} lora · rank \d: done in ", x)]) == 2
    assert len([x for x in lines if re.match(rf"{stamp} trial 'rank \d' finished", x)]) == 2
    assert beats >= 2
    (events,) = (toy.work / "logs").glob("sweep-toy_ablation-*/events.jsonl")
    done = [e for e in read_events(events) if e.kind == "stage" and e.state in ("done", "cached")]
    assert sorted(e.stage for e in done) == ["distill", "evaluate_qa", "evaluate_qa", "lora", "lora", "reconstruct",
                                             "tokenizer"]  # fmt: skip


def test_a_stage_whose_setup_raises_says_one_cause_and_blocks_downstream(tmp_path):
    toy = Toy(tmp_path)
    # heartbeats off: how many a loaded machine prints is timing; the piped sweep's test checks them
    r = toy.run("run.heartbeat_s=3600", GDWM_TEST_FAIL="reconstruct:setup")
    out = (r.stdout + r.stderr).splitlines()
    assert r.returncode == 1 and len(out) <= 3, out
    cause = "stage 'reconstruct' failed in setup: KeyError: 'GDWM_TEST_MISSING_VARIABLE'; traceback: "
    final = next(x for x in out if x.startswith("gdwm run: "))
    assert final.startswith(f"gdwm run: {cause}{toy.work}/logs/run-toy-") and final.endswith(
        "; 6 stage(s) downstream blocked"
    )
    path = Path(final.removeprefix(f"gdwm run: {cause}").split(";")[0])
    assert "KeyError: 'GDWM_TEST_MISSING_VARIABLE'" in path.read_text() and "_setup" in path.read_text()
    # each scene actor ran setup once, nothing retried: at most the pool's 2 actors (a loaded machine may fail the
    # stage before the second one starts), no actor id twice (a restarted actor keeps its id in a new process)
    actors = [line.split()[1] for line in (tmp_path / "setups.log").read_text().splitlines()]
    assert 1 <= len(actors) <= 2 and len(set(actors)) == len(actors), actors
    (events,) = (toy.work / "logs").glob("run-toy-*/events.jsonl")
    states = {e.stage: e.state for e in read_events(events) if e.kind == "stage" and e.state != "running"}
    assert states == {"reconstruct": "failed", **dict.fromkeys(
        ["distill", "tokenizer", "lora", "evaluate_qa", "diffusion", "evaluate_gen"], "blocked")}  # fmt: skip
    assert "Token authentication" not in r.stderr
