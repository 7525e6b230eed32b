"""The launch's progress state, its two renderings and its events file, in process (no Ray): states and shared
executions, counts and ETA, log lines with timestamp and x/N, heartbeats at the configured interval, the board in a
terminal emulator (pyte), the snapshot a dashboard reads."""

from __future__ import annotations

import io
import json
import re

import pyte
import pytest
from rich.console import Console
from rich.live import Live

from gdwm.board import Lines, board
from gdwm.events import Event, EventLog, read_events
from gdwm.progress import Execution, LaunchProgress, duration
from gdwm.term import VERBOSE

K = {s: s[0] * 64 for s in ("reconstruct", "tokenizer")}
K_LORA = {"rank 4": "4" * 64, "rank 8": "8" * 64}


class Clock:
    def __init__(self, t: float = 1_000_000.0):
        self.t = t

    def __call__(self) -> float:
        return self.t


def _sweep(clock: Clock) -> LaunchProgress:
    """Two trials sharing reconstruct (3 scenes) and tokenizer, each with its own lora."""
    trials = {label: [("reconstruct", K["reconstruct"]), ("tokenizer", K["tokenizer"]), ("lora", k)]
              for label, k in K_LORA.items()}  # fmt: skip
    execs = [
        Execution("reconstruct", K["reconstruct"], list(K_LORA), scenes_total=3, estimate_s=30.0),
        Execution("tokenizer", K["tokenizer"], list(K_LORA), estimate_s=10.0),
        *(Execution("lora", k, [label], estimate_s=20.0) for label, k in K_LORA.items()),
    ]
    return LaunchProgress("sweep", "toy", "sweep-toy-1", trials, execs, clock)


def _ev(clock: Clock, kind: str, state: str | None = None, stage: str = "", key: str = "", **kw) -> Event:
    return Event(kind, state, stage or None, key or None, t=clock(), **kw)


def test_states_shared_counts_and_eta():
    clock = Clock()
    lp = _sweep(clock)
    assert lp.eta_s() == 30 + 10 + 20 + 20  # nothing started: every estimate, one after another
    lp.feed(_ev(clock, "stage", "running", "reconstruct", K["reconstruct"]))
    clock.t += 10
    lp.feed(_ev(clock, "scene", "done", "reconstruct", K["reconstruct"], scene="scene-0000"))
    # its own rate now: 1 of 3 scenes in 10 s -> 20 s left; then the pending ones
    assert lp.executions["reconstruct", K["reconstruct"]].remaining_s(clock()) == 20
    assert lp.eta_s() == 20 + 10 + 20 + 20
    clock.t += 20
    lp.feed(_ev(clock, "stage", "done", "reconstruct", K["reconstruct"]))
    assert lp.cell("rank 4", "reconstruct")[0] == "done" and lp.cell("rank 8", "reconstruct")[0] == "shared"
    lp.feed(_ev(clock, "stage", "running", "lora", K_LORA["rank 8"]))
    lp.feed(_ev(clock, "step", None, "lora", K_LORA["rank 8"], step=5, steps=20, loss=0.5))
    clock.t += 5
    assert lp.executions["lora", K_LORA["rank 8"]].remaining_s(clock()) == 15  # 5 steps in 5 s, 15 to go
    lp.feed(_ev(clock, "stage", "failed", "lora", K_LORA["rank 8"], cause="stage 'lora' failed: ValueError: x"))
    lp.feed(_ev(clock, "trial", "failed", trials=["rank 8"]))
    assert lp.trial_state("rank 8") == "failed" and lp.trial_state("rank 4") == "running"
    assert lp.counts() == {"executions": 4, "executions_finished": 2, "trials": 2, "trials_done": 0,
                           "trials_failed": 1}  # fmt: skip
    # an outcome is final: a late worker event does not undo it
    lp.feed(_ev(clock, "stage", "running", "lora", K_LORA["rank 8"]))
    assert lp.executions["lora", K_LORA["rank 8"]].state == "failed"


def test_this_launchs_own_durations_replace_the_stores():
    clock = Clock()
    lp = _sweep(clock)
    lp.feed(_ev(clock, "stage", "running", "lora", K_LORA["rank 4"]))
    clock.t += 50
    lp.feed(_ev(clock, "stage", "done", "lora", K_LORA["rank 4"]))
    assert lp.executions["lora", K_LORA["rank 8"]].estimate_s == 50  # was 20 from the store


def test_lines_have_timestamp_count_trials_and_duration():
    clock = Clock()
    lp = _sweep(clock)
    lines = Lines(lp)
    ev = _ev(clock, "stage", "running", "tokenizer", K["tokenizer"])
    assert lines.line(ev, lp.feed(ev)) is None  # starts only with --verbose
    clock.t += 12.3
    ev = _ev(clock, "stage", "done", "tokenizer", K["tokenizer"], duration_s=12.3)
    line = lines.line(ev, lp.feed(ev))
    assert re.fullmatch(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d \[1/4\] tokenizer · rank 4, rank 8: done in 12 s "
                        r"\(shared by 2 trials\) · trials 0/2", line), line  # fmt: skip
    ev = _ev(clock, "trial", "done", trials=["rank 4"], message="finished (3 metrics)")
    lp.feed(ev)
    assert lines.line(ev, None).endswith("[1/4] trial 'rank 4' finished (3 metrics) · trials 1/2")
    verbose = Lines(lp, VERBOSE)
    ev = _ev(clock, "stage", "running", "lora", K_LORA["rank 8"])
    assert verbose.line(ev, lp.feed(ev)).endswith("[1/4] lora · rank 8: running")


def test_heartbeat_every_interval_with_step_loss_and_eta():
    clock = Clock()
    lp = _sweep(clock)
    lines = Lines(lp, heartbeat_s=5)
    lp.feed(_ev(clock, "stage", "running", "lora", K_LORA["rank 4"]))
    lp.feed(_ev(clock, "step", None, "lora", K_LORA["rank 4"], step=2, steps=8, loss=0.25))
    assert lines.heartbeats(clock() + 4.9) == []
    (beat,) = lines.heartbeats(clock() + 5)
    assert beat.endswith("[0/4] lora · rank 4: running 5.0 s, step 2/8, loss 0.25, ETA 15 s"), beat
    assert lines.heartbeats(clock() + 9) == []  # the next one is due 5 s after this one
    assert len(lines.heartbeats(clock() + 10)) == 1


def test_board_redraws_in_a_terminal_emulator():
    """The live board drawn by rich into a pyte screen: trials done rises as trials finish."""
    clock = Clock()
    lp = _sweep(clock)
    out = io.StringIO()
    console = Console(file=out, force_terminal=True, width=120, height=30, color_system=None)
    screen = pyte.Screen(120, 30)
    stream = pyte.Stream(screen)
    seen = []
    with Live(board(lp), console=console, auto_refresh=False) as live:
        for label in K_LORA:
            clock.t += 10
            lp.feed(_ev(clock, "trial", "done", trials=[label]))
            live.update(board(lp), refresh=True)
            stream.feed(out.getvalue().replace("\n", "\r\n"))  # what a tty driver does (onlcr)
            out.truncate(0), out.seek(0)
            seen.append(re.search(r"trials (\d)/2 done", "\n".join(screen.display)).group(1))
    assert seen == ["1", "2"]
    assert any("rank 4" in line and "done" in line for line in screen.display)


def test_snapshot_is_json_with_every_trial_and_stage():
    clock = Clock()
    lp = _sweep(clock)
    lp.feed(_ev(clock, "stage", "running", "reconstruct", K["reconstruct"]))
    lp.feed(_ev(clock, "scene", "done", "reconstruct", K["reconstruct"], scene="scene-0001"))
    snap = json.loads(json.dumps(lp.snapshot("logs/x/events.jsonl")))
    assert snap["state"] == "running" and snap["events"] == "logs/x/events.jsonl"
    assert snap["stages"] == ["reconstruct", "tokenizer", "lora"]
    cell = snap["trials"]["rank 8"]["stages"]["reconstruct"]
    assert cell["state"] == "running" and cell["scenes_done"] == 1 and cell["scenes_total"] == 3
    assert snap["trials"]["rank 8"]["stages"]["lora"] == {"state": "pending", "key": K_LORA["rank 8"], "eta_s": 20.0}


def test_events_file_round_trips_and_skips_a_partial_line(tmp_path):
    path = tmp_path / "events.jsonl"
    log = EventLog(path)
    log.write(Event("stage", "done", "lora", "k" * 64, trials=["rank 4"], duration_s=1.5, t=12.0))
    log.close()
    with open(path, "a") as f:
        f.write('{"t": 13.0, "kind": "st')  # the launch is writing its next line
    (ev,) = list(read_events(path))
    assert ev == Event("stage", "done", "lora", "k" * 64, trials=["rank 4"], duration_s=1.5, t=12.0)
    assert json.loads(path.read_text().splitlines()[0]) == {
        "t": 12.0, "kind": "stage", "state": "done", "stage": "lora", "key": "k" * 64, "trials": ["rank 4"],
        "duration_s": 1.5}  # fmt: skip


def test_an_unknown_state_is_refused_naming_it():
    with pytest.raises(ValueError, match="event state 'waiting' is not one of"):
        Event("stage", "waiting")


@pytest.mark.parametrize(("seconds", "shown"), [(4.24, "4.2 s"), (42, "42 s"), (185, "3 min 05 s"),
                                                (3720, "1 h 02 min"), (None, "?")])  # fmt: skip
def test_duration(seconds, shown):
    assert duration(seconds) == shown


class _Queue:
    """What a Reporter holds of the progress actor: ``put.remote(event)``; here it records and signals."""

    def __init__(self):
        import threading
        from types import SimpleNamespace

        self.events: list[dict] = []
        self.arrived = threading.Event()
        self.put = SimpleNamespace(remote=self._put)

    def _put(self, event: dict) -> None:
        self.events.append(event)
        self.arrived.set()


def test_a_thinned_step_is_sent_when_its_interval_ends():
    # A stage that stops reporting (blocked at step 1, or inside a long step) must still show the step it reached:
    # step 1 comes too soon after step 0 and is held, then sent by the trailing edge, not dropped.
    from gdwm.progress import Reporter

    q = _Queue()
    r = Reporter(q, "lora", "k" * 64)
    r.step(0, 3, 1.0)
    assert [e["step"] for e in q.events] == [0]
    q.arrived.clear()
    r.step(1, 3, 0.5)
    assert [e["step"] for e in q.events] == [0]  # held
    assert q.arrived.wait(timeout=30)  # the interval's end, not a fixed sleep
    assert [(e["step"], e["loss"]) for e in q.events] == [(0, 1.0), (1, 0.5)]
    r.step(3, 3, 0.25)  # the final step goes at once
    assert [e["step"] for e in q.events] == [0, 1, 3]
