"""The environment record (gdwm.environment.record): what it holds, what its digest covers, the code state of a git
tree, the differences between two records in words, and what compare and regress say about them on a real store."""

from __future__ import annotations

import copy
import subprocess
import sys

import pytest
import torch

from gdwm.compare.runs import Row, Trial
from gdwm.environment.differences import brief, differences
from gdwm.environment.lock import venv_lock
from gdwm.environment.record import THREAD_VARS, code_state, commit_tag, digest, environment, summary
from gdwm.environment.runs import DIGEST_TAG, RECORD_RUN_TAG, baseline_flags, environment_note, tag_run


@pytest.fixture(scope="module")
def rec() -> dict:
    return environment()


OTHER_CAP = "AVX2" if torch.backends.cpu.get_cpu_capability() != "AVX2" else "AVX512"
"""A CPU capability this machine's is not: what another machine's record says."""


def test_the_record_holds_what_the_issue_lists(rec):
    assert rec["python"]["version"] == ".".join(map(str, sys.version_info[:3]))
    assert rec["torch"]["version"] == torch.__version__ and rec["torch"]["git"] == torch.version.git_version
    assert rec["cpu"]["capability"] == torch.backends.cpu.get_cpu_capability()
    assert rec["threads"]["torch"] == torch.get_num_threads()
    assert rec["distributions"]["torch"] == torch.__version__
    import mlflow
    import ray

    assert (rec["ray"], rec["mlflow"]) == (ray.__version__, mlflow.__version__)
    assert "gdwm" in rec["editable"] and "gdwm" in rec["distributions"]
    assert rec["cpu"]["model"] and rec["cpu"]["usable"] >= 1
    assert rec["gpu"] is None or rec["gpu"]["devices"]
    code = rec["gdwm"]
    assert len(code["commit"]) == 40 and isinstance(code["dirty"], bool)
    if venv_lock() is not None:
        assert rec["lock"]["name"].startswith(("cpu-", "cuda-")) and rec["lock"]["matches"] is True, rec["lock"]
    assert len(rec["digest"]) == 12 and digest(rec) == rec["digest"]
    assert environment() is rec  # once per process


def test_the_digest_leaves_out_host_time_and_code_only(rec):
    other = copy.deepcopy(rec)
    other.update(host="elsewhere", recorded_at="2030-01-01T00:00:00+00:00", launch={"cwd": "/x"})
    other["gdwm"] = {"commit": "0" * 40, "dirty": True, "diff_sha256": "1" * 64}
    assert digest(other) == rec["digest"]
    for path, value in ((("cpu", "capability"), OTHER_CAP), (("threads", "torch"), 64),
                        (("distributions", "numpy"), "0.0.1")):  # fmt: skip
        changed = copy.deepcopy(rec)
        changed[path[0]][path[1]] = value
        assert digest(changed) != rec["digest"], path


def test_differences_in_words(rec):
    b = copy.deepcopy(rec)
    b["cpu"]["capability"] = OTHER_CAP
    b["distributions"]["toylib"] = "2.0"
    b["distributions"].pop("scipy")
    b["threads"]["OMP_NUM_THREADS"] = "4"
    b["gdwm"] = dict(rec["gdwm"], commit="f" * 40, dirty=False)
    lines = differences(rec, b)
    assert lines == [
        f"gdwm {commit_tag(rec)} -> {'f' * 12}",
        f"CPU capability {rec['cpu']['capability']} -> {OTHER_CAP}",
        f"OMP_NUM_THREADS {rec['threads'].get('OMP_NUM_THREADS', 'unset')} -> 4",
        f"scipy {rec['distributions']['scipy']} -> absent",
        "toylib absent -> 2.0",
    ]
    assert differences(rec, b, code=False) == lines[1:]
    assert differences(rec, copy.deepcopy(rec)) == []
    assert brief(lines, 2) == f"{lines[0]}; {lines[1]}; and 3 more"


def _git(root, *args):
    subprocess.run(["git", "-C", str(root), *args], check=True, capture_output=True)


def test_code_state_of_a_git_tree(tmp_path, monkeypatch):
    _git(tmp_path, "init", "-q")
    (tmp_path / "a.py").write_text("x = 1\n")
    _git(tmp_path, "add", "a.py")
    _git(tmp_path, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "one")
    clean = code_state(tmp_path)
    assert clean["dirty"] is False and clean["diff_sha256"] is None and len(clean["commit"]) == 40
    (tmp_path / "a.py").write_text("x = 2\n")
    edited = code_state(tmp_path)
    assert edited["dirty"] is True and edited["commit"] == clean["commit"]
    (tmp_path / "b.py").write_text("y = 1\n")  # an untracked file is part of what ran
    untracked = code_state(tmp_path)
    assert untracked["diff_sha256"] != edited["diff_sha256"]
    (tmp_path / "b.py").write_text("y = 2\n")
    assert code_state(tmp_path)["diff_sha256"] != untracked["diff_sha256"]
    assert commit_tag({"gdwm": untracked}) == f"{clean['commit'][:12]}+dirty.{untracked['diff_sha256'][:8]}"
    monkeypatch.setenv("GDWM_COMMIT", "abc123")  # an installed wheel (the Ray image) knows its commit this way
    assert code_state(tmp_path / "nowhere") == {"commit": "abc123", "dirty": None, "diff_sha256": None}


# ---- on a real MLflow store: compare's note and regress's flag --------------------------------------------------
@pytest.fixture(scope="module")
def store(tmp_path_factory, rec):
    from gdwm.tracking import TrackingBackend

    root = tmp_path_factory.mktemp("envstore")
    backend = TrackingBackend(f"sqlite:///{root}/mlflow.db", "gdwm", str(root / "art"))
    other = copy.deepcopy(rec)
    other["cpu"]["capability"] = OTHER_CAP
    other["distributions"]["toylib"] = "2.0"
    other["digest"] = digest(other)
    runs = {}
    for name, r in (("here", rec), ("there", other)):
        runs[name] = backend.create_run(name, {"gdwm.kind": "trial"})
        tag_run(backend, runs[name], r)
        backend.end_run(runs[name])
    runs["old"] = backend.create_run("old", {"gdwm.kind": "trial"})
    backend.end_run(runs["old"])
    return backend, runs, other


def _row(backend, label: str, run_id: str) -> Row:
    tags = dict(backend.client.get_run(run_id).data.tags)
    return Row(run_id, label, "FINISHED", "0", {}, tags=tags, trials=[Trial(run_id, 0, "FINISHED", {}, tags)])


def test_compare_notes_rows_from_other_environments(store, rec):
    backend, runs, other = store
    same = [_row(backend, "A", runs["here"]), _row(backend, "B", runs["here"])]
    assert environment_note(backend, same) is None
    note = environment_note(backend, [*same, _row(backend, "C", runs["there"]), _row(backend, "D", runs["old"])])
    cap = rec["cpu"]["capability"]
    assert note == (
        "Environments differ between rows (numbers may move by float rounding across CPUs and library versions): "
        f"A, B: environment {rec['digest']} ({summary(rec)}); C: environment {other['digest']}, which differs from "
        f"{rec['digest']} in: CPU capability {cap} -> {OTHER_CAP}; toylib absent -> 2.0; D: no environment recorded "
        "(an older gdwm)."
    )
    assert backend.client.get_run(runs["there"]).data.tags[RECORD_RUN_TAG] == runs["there"]
    assert backend.client.get_run(runs["there"]).data.tags[DIGEST_TAG] == other["digest"]


def test_regress_flags_a_baseline_from_another_environment(store, rec):
    backend, runs, other = store
    assert baseline_flags(backend, runs["here"], rec) == []
    [flag] = baseline_flags(backend, runs["there"], rec)
    assert flag == (
        f"baseline run {runs['there'][:12]} ran in another environment ({other['digest']} -> {rec['digest']}: CPU "
        f"capability {OTHER_CAP} -> {rec['cpu']['capability']}; toylib 2.0 -> absent): float rounding may move its "
        "numbers; re-record it here with --set-baseline"
    )
    [old] = baseline_flags(backend, runs["old"], rec)
    assert old.startswith(f"baseline run {runs['old'][:12]} recorded no environment (an older gdwm)")


RECORD = "import json, sys; from gdwm.environment.record import environment; r = environment(); " \
         "print(json.dumps([r['digest'], r['torch'], r['threads'], 'torch' in sys.modules]))"  # fmt: skip


def test_a_process_without_torch_reads_its_facts_from_the_last_computation(tmp_path, rec):
    import json

    env = {**__import__("os").environ, "GDWM_LOCAL_CACHE": str(tmp_path)}

    def record() -> list:
        r = subprocess.run([sys.executable, "-c", RECORD], capture_output=True, text=True, env=env, timeout=120)
        assert r.returncode == 0, r.stderr
        return json.loads(r.stdout)

    first = record()  # computed: torch imported, the facts written for this install
    (written,) = (tmp_path / "environment").glob("torch-*.json")
    second = record()
    assert first[3] is True and second[3] is False  # the second process never imported torch
    assert second[:3] == first[:3] == [rec["digest"], rec["torch"], rec["threads"]]
    assert json.loads(written.read_text())["torch"]["config"] == torch.__config__.show()
    env["OMP_NUM_THREADS"] = "1"  # what sets torch's threads is part of the file's name: computed again
    expected = {v: env[v] for v in THREAD_VARS if v in env}  # the thread variables the process saw
    assert record()[2] == {"torch": 1, "torch_interop": rec["threads"]["torch_interop"], **expected}
    assert len(list((tmp_path / "environment").glob("torch-*.json"))) == 2
