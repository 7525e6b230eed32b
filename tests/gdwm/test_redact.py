"""Credentials never reach MLflow or the terminal: URIs' user:password@, secret query parameters and the values of
the secret environment variables are masked wherever gdwm prints or logs (issue 16)."""

from __future__ import annotations

import io
import json
import subprocess
import sys
from pathlib import Path

import mlflow
import pytest
from rich.table import Table

from gdwm.cache import MANIFEST
from gdwm.redact import MASK, redact, redact_config
from gdwm.term import RedactingConsole
from gdwm.tracking import flatten_params
from tests.gdwm.test_run import Toy

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("https://alice:pw@host/x", "https://alice:***@host/x"),
        ("s3://KEY:SECRET@bucket/p", "s3://KEY:***@bucket/p"),
        ("postgresql://u:p@db:5432/mlflow", "postgresql://u:***@db:5432/mlflow"),
        ("https://ghp_tok3n@host/repo", "https://***@host/repo"),
        ("http://h:5000/x?token=abc&x=1", "http://h:5000/x?token=***&x=1"),
        ("https://b.s3.amazonaws.com/k?X-Amz-Signature=ab12&X-Amz-Credential=AK%2F1", "https://b.s3.amazonaws.com/k?X-Amz-Signature=***&X-Amz-Credential=***"),
        ("https://acct.blob.core.windows.net/c?sv=2024&sig=ZmFrZQ%3D", "https://acct.blob.core.windows.net/c?sv=2024&sig=***"),
        ("gs://b/p?access_token=ya29.x&password=hunter2&api_key=k1", "gs://b/p?access_token=***&password=***&api_key=***"),
        ("server https://alice:p@ss@host/api: 401", "server https://alice:***@host/api: 401"),
    ],
)  # fmt: skip
def test_redact_masks_credentials(text, expected):
    assert redact(text) == expected


@pytest.mark.parametrize(
    "text",
    [
        "sqlite:////tmp/w/mlflow.db",
        "s3://bucket/cache",
        "https://mlflow.example.com:5000/#/experiments/1?monkey=1&x=2",
        "/data/gdwm/cache",
        "mail bob@example.com about http://host/a@b",
        "",
    ],
)
def test_redact_leaves_text_without_secrets_unchanged(text):
    assert redact(text) == text


def test_redact_masks_values_of_secret_environment_variables(monkeypatch):
    monkeypatch.setenv("MLFLOW_TRACKING_PASSWORD", "hunter2-for-mlflow")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "wJalrXUtnFEMI/K7MDENG")
    monkeypatch.setenv("MLFLOW_TRACKING_USERNAME", "alice-the-user")  # a name, not a secret
    msg = "login as alice-the-user with hunter2-for-mlflow failed; s3 key wJalrXUtnFEMI/K7MDENG refused"
    assert redact(msg) == f"login as alice-the-user with {MASK} failed; s3 key {MASK} refused"


def test_redact_config_walks_a_plain_config():
    cfg = {
        "tracking": {"uri": "https://alice:pw@host", "experiment": "gdwm"},
        "cache": {"uri": "s3://KEY:SECRET@bucket/c"},
        "seeds": [0, 1],
        "mirrors": ["https://u:p@m1/x", "plain"],
        "lr": 0.1,
        "on": True,
        "none": None,
    }
    assert redact_config(cfg) == {
        "tracking": {"uri": "https://alice:***@host", "experiment": "gdwm"},
        "cache": {"uri": "s3://KEY:***@bucket/c"},
        "seeds": [0, 1],
        "mirrors": ["https://u:***@m1/x", "plain"],
        "lr": 0.1,
        "on": True,
        "none": None,
    }
    assert cfg["tracking"]["uri"] == "https://alice:pw@host"  # a copy: what connects keeps the credentials


def test_params_and_consoles_mask_credentials():
    params = flatten_params({"tracking": {"uri": "https://alice:pw@host"}, "l": ["s3://K:SECRET@b/p"]})
    assert params == {"tracking.uri": "https://alice:***@host", "l": '["s3://K:***@b/p"]'}
    out = io.StringIO()
    RedactingConsole(file=out, width=200).print("store https://alice:pw@host unreadable", markup=False)
    assert out.getvalue() == "store https://alice:***@host unreadable\n"


def test_a_piped_line_of_text_stays_one_line_and_a_table_keeps_the_width():
    """A 202-character line (a sim cluster's placement, say) reaches a pipe whole at width 160; a table does not
    grow past the width; a terminal still wraps text at its width."""
    node = "sim-worker-{}: RayTrainWorker x4, SceneWorker x2, _Answerer x1"
    line = "sim placement: " + "; ".join(node.format(i) for i in (1, 2, 3))
    out = io.StringIO()
    console = RedactingConsole(file=out, width=160, highlight=False)
    console.print(line, markup=False)
    table = Table("a", "b")
    table.add_row("x" * 120, "y" * 120)
    console.print(table)
    lines = out.getvalue().splitlines()
    assert len(line) > 160 and lines[0] == line
    assert max(len(ln) for ln in lines[1:]) == 160
    tty = io.StringIO()
    RedactingConsole(file=tty, width=160, force_terminal=True, color_system=None).print(line, markup=False)
    wrapped = tty.getvalue().splitlines()
    assert len(wrapped) == 2 and max(len(ln) for ln in wrapped) <= 160 and " ".join(wrapped).split() == line.split()


def test_config_show_masks_credentials():
    r = subprocess.run(
        [sys.executable, "-m", "gdwm", "config", "show", "tracking.uri=https://alice:pw@host",
         "cache.uri='s3://KEY:SECRET@bucket/cache?X-Amz-Security-Token=T0KEN'"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    out = r.stdout + r.stderr
    assert "alice:pw@" not in out and "SECRET" not in out and "T0KEN" not in out
    assert "uri: https://alice:***@host" in r.stdout
    assert "uri: s3://KEY:***@bucket/cache?X-Amz-Security-Token=***" in r.stdout


# the params and console tests above fail on leaking code in seconds; this is the whole path through a real run
def test_run_logs_no_credentials_to_mlflow(tmp_path):
    """A real `gdwm run` whose cache URI carries a token (the local filesystem ignores it): the cache is used as
    given, while no param or tag of any run, and nothing printed, carries the token."""
    toy = Toy(tmp_path)
    secret = "s3cr3t-T0KEN-value"
    cache_dir = tmp_path / "cache"
    r = toy.run(f"cache.uri='file://{cache_dir}?token={secret}'", "targets=[reconstruct]")
    assert r.returncode == 0, f"STDOUT\n{r.stdout[-3000:]}\nSTDERR\n{r.stderr[-5000:]}"
    assert secret not in r.stdout + r.stderr
    assert any(p.name == MANIFEST for p in cache_dir.rglob("*"))  # the real URI reached the cache
    client = mlflow.MlflowClient(f"sqlite:///{toy.work.resolve()}/mlflow.db")
    exp = client.get_experiment_by_name("gdwm")
    runs = client.search_runs([exp.experiment_id], max_results=1000)
    kinds = {x.data.tags.get("gdwm.kind") for x in runs}
    assert {"run", "stage"} <= kinds, kinds
    (parent,) = [x for x in runs if x.data.tags.get("gdwm.kind") == "run"]
    assert parent.data.params["cache.uri"] == f"file://{cache_dir}?token={MASK}"
    for x in runs:
        assert not [k for k, v in {**x.data.params, **x.data.tags}.items() if secret in v], x.info.run_name


def test_a_secret_from_the_environment_reaches_the_stage_and_nothing_gdwm_writes(tmp_path):
    """``${oc.env:HF_TOKEN}`` in a stage's config (a name redact() does not know): the stage reads the value, while
    no manifest, param, tag, artifact or plan holds it, and the cache key stays the same when the secret rotates."""
    toy = Toy(tmp_path)
    old, new = "hf_OLDsecretOLDsecretOLD", "hf_NEWsecretNEWsecretNEW"
    token = "+stage.toy_tokenizer.token=${oc.env:HF_TOKEN}"
    r = toy.run(token, "targets=[tokenizer]", "run.live=false", HF_TOKEN=old)
    assert r.returncode == 0, f"STDOUT\n{r.stdout[-3000:]}\nSTDERR\n{r.stderr[-5000:]}"
    assert (tmp_path / "token-seen").read_text() == old
    leaked = [p.relative_to(toy.work).as_posix() for p in toy.work.rglob("*") if p.is_file() and old.encode() in
              p.read_bytes()]  # fmt: skip
    assert leaked == [] and old not in r.stdout + r.stderr
    (manifest,) = [p for p in (toy.work / "cache" / "tokenizer").rglob(MANIFEST)]
    assert json.loads(manifest.read_text())["config"]["stage.toy_tokenizer"]["token"] == "<env:HF_TOKEN>"
    # the secret rotates: the plan re-runs nothing and prints neither value
    r = subprocess.run([*toy.args(token, "targets=[tokenizer]", "--dry-run")], env=toy.env(HF_TOKEN=new),
                       capture_output=True, text=True, timeout=300)  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    assert old not in r.stdout + r.stderr and new not in r.stdout + r.stderr
    assert "7 cached, 0 to run" in r.stdout and "why stages re-run" not in r.stdout
