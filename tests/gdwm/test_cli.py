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
    assert "data       gaussiandwm_release, nuscenes, synthetic_mini" in r.stdout
    assert "cluster    a100x16, local" in r.stdout


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
