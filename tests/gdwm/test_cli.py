"""The gdwm CLI: help, unknown commands, exit codes."""

import subprocess
import sys


def _gdwm(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "gdwm", *args], capture_output=True, text=True)


def test_help_lists_commands_and_groups():
    r = _gdwm("--help")
    assert r.returncode == 0
    for text in ("data synth", "data import-gaussiandwm", "data convert-nuscenes", "data info", "config show"):
        assert text in r.stdout
    assert "data       gaussiandwm_release, nuinstruct, nuinteract, nuscenes, omnidrive, synthetic_mini" in r.stdout
    assert "cluster    a100x16, local, sim" in r.stdout
    assert "experiment demo, gaussiandwm_pp" in r.stdout
    assert "sweep      conference_ablation, dual_condition, journal_ablation" in r.stdout


def test_subcommand_help():
    r = _gdwm("data", "--help")
    assert r.returncode == 0
    assert r.stdout.startswith("usage: gdwm data <subcommand> [overrides...]")
    r = _gdwm("data", "synth", "--help")
    assert r.returncode == 0
    assert r.stdout.startswith("usage: gdwm data synth [overrides...]")


def test_unknown_command_and_subcommand_exit_2():
    r = _gdwm("dta", "synth")
    assert r.returncode == 2
    assert "gdwm: unknown command 'dta'; commands: data, config" in r.stderr
    r = _gdwm("data", "sinth")
    assert r.returncode == 2
    assert "gdwm data: unknown subcommand 'sinth'; subcommands: synth, import-gaussiandwm" in r.stderr
    r = _gdwm("data", "synth", "--fast")
    assert r.returncode == 2
    assert "unknown flag(s) ['--fast']" in r.stderr


def test_no_arguments_prints_usage_and_exits_2():
    r = _gdwm()
    assert r.returncode == 2
    assert r.stdout.startswith("usage: gdwm <command>")


def test_plugin_commands_are_listed_and_check_their_arguments(tmp_path):
    r = _gdwm("--help")
    assert "generate                   generate shifted / future views of a frame" in r.stdout
    assert "edit                       edit a clip by instruction" in r.stdout
    r = _gdwm("generate", f"workdir={tmp_path}")  # args.scene missing: nothing is launched
    assert r.returncode == 1
    assert "gdwm generate: CommandError: args.scene is required" in r.stderr
    r = _gdwm("generate", f"workdir={tmp_path}", "args.sceen=x")
    assert r.returncode == 2 and "args.sceen" in r.stderr


def test_data_synth_prints_the_dataset_summary(tmp_path):
    import re

    import pyarrow.parquet as pq

    def cells(line: str) -> list[str]:  # a rich table row (header ┃, body │) as stripped cells
        return [c.strip() for c in re.split("[│┃]", line)[1:-1]]

    r = _gdwm("data", "synth", f"workdir={tmp_path}", "data.num_scenes=1", "data.width=48", "data.height=27")
    assert r.returncode == 0, r.stderr
    root = tmp_path / "data" / "synthetic_mini"
    # the counts are recomputed from the files, not taken from the summarizer
    qa = pq.read_table(root / "qa.parquet").column("task").to_pylist()
    on_disk = sum(p.stat().st_size for p in root.rglob("*") if p.is_file() and p.name != "dataset.json")
    lines = r.stdout.splitlines()
    assert lines[0].startswith("built synthetic_mini in ")
    header = next(i for i, x in enumerate(lines) if "scenes" in x and "on disk" in x)
    row = cells(lines[header + 2])  # scenes, frames, cameras, weathers, boxes, QA, files, on disk
    assert row[:4] == ["1", "10", "6", "clear,fog,night,rain"]
    assert row[6] == str(len(qa))
    assert abs(float(row[8].split()[0]) - on_disk / 2**20) < 0.15  # MiB, one decimal (dataset.json excluded)
    tasks = next(i for i, x in enumerate(lines) if "QA per task family" in x)
    names = cells(lines[tasks + 2])
    counts = [int(c) for c in cells(lines[tasks + 4])]
    assert names == ["rdp", "vg2d", "vg3d", "plan", "traj"]
    assert dict(zip(names, counts, strict=True)) == {t: qa.count(t) for t in names}
    assert sum(counts) == len(qa)


def test_status_of_a_workdir_where_nothing_ran_creates_nothing(tmp_path):
    work = tmp_path / "nowhere"
    r = _gdwm("status", f"workdir={work}")
    assert r.returncode == 1
    assert f"no MLflow store at {work.resolve()}/mlflow.db: nothing has run in workdir" in r.stderr.replace("\n", "")
    assert not work.exists()


def test_plugin_subcommands_come_before_the_built_in_ones_and_may_not_clash(monkeypatch):
    import pytest

    from gdwm import cli
    from gdwm.config import ConfigError

    def run(cfg, args):
        return 0

    monkeypatch.setattr(
        cli, "COMMANDS", {"data": {"info": cli.Command(run, "built in")}, "run": {"": cli.Command(run, "")}}
    )
    cli._add_subcommands("data", "plug:DATA", {"make": cli.Command(run, "plugged", ["data=x"])})
    assert list(cli.COMMANDS["data"]) == ["make", "info"]
    assert cli.COMMANDS["data"]["make"].defaults == ["data=x"]
    cli._add_subcommands("new", "plug:NEW", {"one": cli.Command(run, "")})
    assert list(cli.COMMANDS) == ["data", "run", "new"]
    with pytest.raises(ConfigError, match=r"^plugin subcommand 'data info' \(plug:X\) clashes with a built-in"):
        cli._add_subcommands("data", "plug:X", {"info": cli.Command(run, "")})
    with pytest.raises(ConfigError, match=r"^plugin subcommands 'run' \(plug:X\): 'gdwm run' is a built-in command"):
        cli._add_subcommands("run", "plug:X", {"sub": cli.Command(run, "")})
    with pytest.raises(ConfigError, match=r"^plugin subcommand 'data bad' \(plug:X\): expected a gdwm.cli.Command"):
        cli._add_subcommands("data", "plug:X", {"bad": run})


def test_the_data_commands_are_the_plugins():
    from importlib.metadata import entry_points

    from gdwm.cli import COMMAND_GROUP

    (ep,) = [e for e in entry_points(group=COMMAND_GROUP) if e.name == "data"]
    subs = ep.load()
    assert list(subs) == ["synth", "import-gaussiandwm", "export-gaussiandwm", "convert-nuscenes", "import-nuinteract",
                          "import-nuinstruct", "import-omnidrive"]  # fmt: skip
    assert subs["import-gaussiandwm"].defaults == ["data=gaussiandwm_release"]
    assert subs["convert-nuscenes"].defaults == ["data=nuscenes"]
    assert [subs[f"import-{b}"].defaults for b in ("nuinteract", "nuinstruct", "omnidrive")] == [
        ["data=nuinteract"], ["data=nuinstruct"], ["data=omnidrive"]
    ]  # fmt: skip
    assert subs["synth"].defaults == []
