"""Callables named in config (``data.builder``, ``data.planner``, ``data.summarizer``) resolve only to what gdwm or a
plugin registered: anything else exits 2 naming the key, before any of them is called."""

from __future__ import annotations

import pytest

from gdwm.cli import main

REFUSED = "not a registered function (registered: "


def test_a_summarizer_that_is_not_registered_is_never_called(tmp_path, capsys):
    root = tmp_path / "thesis"
    root.mkdir()
    (root / "chapter1.tex").write_text("years of work")
    rc = main(["data", "info", f"data.root={root}", "data.summarizer=shutil.rmtree"])
    err = " ".join(capsys.readouterr().err.split())
    registered = "pipelines.data.benchmark.render, pipelines.data.summary.render"
    assert rc == 2 and f"gdwm: config error: data.summarizer=shutil.rmtree: {REFUSED}{registered})" in err
    assert (root / "chapter1.tex").read_text() == "years of work"


@pytest.mark.parametrize(
    "argv, key",
    [
        (["data", "synth", "data.num_scenes=1", "data.builder=builtins.print"], "data.builder"),
        (["data", "synth", "data.num_scenes=1", "data.summarizer=os.getcwd"], "data.summarizer"),
        (["run", "--dry-run", "data.planner=builtins.print"], "data.planner"),
        (["run", "--dry-run", "data.summarizer=shutil.rmtree"], "data.summarizer"),
    ],
)
def test_an_unregistered_data_function_exits_2_before_anything_runs(tmp_path, capsys, argv, key):
    rc = main([*argv, f"workdir={tmp_path / 'w'}"])
    out, err = capsys.readouterr()
    assert rc == 2 and f"gdwm: config error: {key}=" in err and REFUSED in err, (out, err)
    assert not (tmp_path / "w").exists()  # nothing generated: every one is checked before the first is called


def test_the_shipped_datasets_functions_are_registered(tmp_path, capsys):
    rc = main(["run", "--dry-run", f"workdir={tmp_path / 'w'}", "data.num_scenes=1", "targets=[reconstruct]"])
    assert rc == 0 and "would generate synthetic_mini (1 scenes)" in " ".join(capsys.readouterr().out.split())
