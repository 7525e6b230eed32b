"""``gdwm <command> [subcommand] [hydra overrides...]``.

Exit codes: 0 success, 1 a command failed (the message names what), 2 usage or config error
(nothing was launched).
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import cache
from importlib.metadata import entry_points
from pathlib import Path

from hydra.utils import get_method
from omegaconf import DictConfig, OmegaConf
from rich.table import Table

from gdwm.config import MAIN_GROUPS, ConfigError, group_options, load_config, sqlite_path, ui_url
from gdwm.errors import CommandError, one_line
from gdwm.redact import redact, redact_config
from gdwm.term import console, err_console


@dataclass
class Command:
    run: Callable[[DictConfig, list[str]], int | None]
    help: str
    defaults: list[str] = field(default_factory=list)
    """Overrides applied before the user's, e.g. the data group an import command implies."""
    flags: tuple[str, ...] = ()
    """``--flags`` the command accepts; they reach ``run`` in its argument list."""
    options: tuple[str, ...] = ()
    """``--flags`` taking a value (``--keep-last 3`` or ``--keep-last=3``); they reach ``run`` as ``--flag=VALUE``."""
    positional: str | None = None
    """The key a first argument without ``=`` sets (``gdwm reproduce RUN_ID`` -> ``args.run=RUN_ID``)."""


def build_data(cfg: DictConfig, _args: list[str]) -> int:
    """``run`` of a plugin's dataset-building command: builds the dataset ``data=`` selects, from ``source=DIR``."""
    from gdwm.datasets import build_dataset

    build_dataset(cfg, source=cfg.source)
    return 0


def _data_info(cfg: DictConfig, _args: list[str]) -> int:
    from gdwm.datasets import verification_line

    for part in get_method(cfg.data.summarizer)(Path(cfg.data.root)):  # the dataset's own lines and tables
        console.print(part)
    console.print(verification_line(Path(cfg.data.root)), markup=False)
    return 0


def _run(cfg: DictConfig, args: list[str]) -> int:
    from gdwm.dag import DagError
    from gdwm.runner import PlanError, RunError, run_pipeline

    try:
        # `gdwm run` has no command defaults: its config is composed from the user's overrides alone, and so is each
        # seed's (seeds=[...])
        summary = run_pipeline(cfg, [a for a in args if not a.startswith("--")], dry_run="--dry-run" in args)
    except (DagError, PlanError) as e:
        err_console.print(f"gdwm run: {'pipeline error: ' if isinstance(e, DagError) else ''}{e}", markup=False)
        return 2
    except RunError as e:
        err_console.print(f"gdwm run: {e}", markup=False)
        return 1
    for t in summary.trials:
        for msg in t.failed.values():
            err_console.print(f"gdwm run: {msg}", markup=False)
    return 0 if summary.ok else 1


def _status(cfg: DictConfig, _args: list[str]) -> int:
    from gdwm.tracking import TrackingBackend

    uri = cfg.tracking.uri
    if (db := sqlite_path(uri)) is not None and not Path(db).is_file():
        # reading must not create a workdir and an empty store where nothing has run
        err_console.print(f"no MLflow store at {db}: nothing has run in workdir "
                          f"{cfg.workdir} (or tracking.uri points elsewhere)", markup=False)  # fmt: skip
        return 1
    backend = TrackingBackend(uri, cfg.tracking.experiment, cfg.tracking.artifact_location)
    runs = backend.search_runs("", max_results=30, order_by=["attributes.start_time DESC"])
    t = Table(title=f"recent runs in {redact(cfg.tracking.uri)}", header_style="bold")
    for col in ("run id", "name", "kind", "stage", "status", "started", "cache key"):
        t.add_column(col)
    for r in runs:
        tags = r["tags"]
        started = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(r["start_time"] / 1000)) if r["start_time"] else ""
        t.add_row(
            r["run_id"][:12],
            r["name"] or "",
            tags.get("gdwm.kind", ""),
            tags.get("gdwm.stage", ""),
            r["status"],
            started,
            tags.get("gdwm.cache_key", "")[:12],
        )
    console.print(t)
    return 0


def _sweep(cfg: DictConfig, args: list[str]) -> int:
    from gdwm.plan import RunError
    from gdwm.sweep import SweepError, load_sweep, report, run_sweep

    t0 = time.perf_counter()
    try:
        summary = run_sweep(cfg, args, dry_run="--dry-run" in args)
    except SweepError as e:
        err_console.print(f"gdwm sweep: {e}", markup=False)
        return 2
    except RunError as e:
        err_console.print(f"gdwm sweep: {e}", markup=False)
        return 1
    if "--dry-run" in args:
        return 0
    n = len(summary.trials)
    console.print(
        f"sweep: {n} trials, {summary.executions} stage executions run "
        f"({summary.naive} as independent runs without a cache), {time.perf_counter() - t0:.0f} s"
    )
    report(cfg, load_sweep(cfg), args)
    work = f" workdir={cfg.workdir}" if cfg.workdir != "./gdwm-work" else ""
    console.print(f"registered variants: gdwm zoo list{work}")
    console.print(f"MLflow UI: gdwm ui{work}  ->  {ui_url(cfg)}")
    for t in summary.trials:
        for stage, msg in list(t.failed.items())[:1]:
            err_console.print(f"gdwm sweep: trial '{t.trial.name}' failed at {stage}: {msg}", markup=False)
    return 0 if summary.ok else 1


def _regress(cfg: DictConfig, args: list[str]) -> int:
    from gdwm.dag import DagError
    from gdwm.regress import RegressError, regress
    from gdwm.runner import RunError

    try:
        return regress(cfg, args)
    except (RegressError, DagError, RunError) as e:
        err_console.print(f"gdwm regress: {e}", markup=False)
        return 2


def _reproduce(cfg: DictConfig, args: list[str]) -> int:
    from gdwm.dag import DagError
    from gdwm.plan import RunError
    from gdwm.reproduce import ReproduceError, reproduce

    try:
        return reproduce(cfg, args)
    except (ReproduceError, DagError) as e:
        err_console.print(f"gdwm reproduce: {e}", markup=False)
        return 2
    except RunError as e:
        err_console.print(f"gdwm reproduce: {e}", markup=False)
        return 1


def _compare(cfg: DictConfig, _args: list[str]) -> int:
    from gdwm.compare.command import compare

    return compare(cfg)


def _ui(cfg: DictConfig, _args: list[str]) -> int:
    """``mlflow server`` on the configured store in the foreground; Ctrl-C (or SIGTERM) stops it, exit 0."""
    import subprocess

    cmd = [sys.executable, "-m", "mlflow", "server", "--backend-store-uri", cfg.tracking.uri, "--workers", "1"]
    cmd += ["--host", cfg.ui.host, "--port", str(cfg.ui.port)]
    if cfg.tracking.artifact_location:  # experiments created in the UI keep their artifacts in the workdir too
        cmd += ["--artifacts-destination", cfg.tracking.artifact_location]
    # Its own process group: stopping it stops the web server workers it spawns too.
    proc = subprocess.Popen(cmd, start_new_session=True)
    console.print(f"MLflow UI for {cfg.tracking.uri}: {ui_url(cfg)}  (Ctrl-C stops it)")

    def stop(_signum, _frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        rc = proc.wait()
        if rc:
            raise CommandError(f"mlflow server exited with status {rc} (command: {' '.join(cmd)})")
        return 0
    except KeyboardInterrupt:
        with contextlib.suppress(ProcessLookupError):  # the group may be gone already
            os.killpg(proc.pid, signal.SIGTERM)
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
        return 0
    finally:
        signal.signal(signal.SIGTERM, previous)


def _zoo(sub: str) -> Callable[[DictConfig, list[str]], int]:
    def run(cfg: DictConfig, _args: list[str]) -> int:
        from gdwm.zoo.command import SUBCOMMANDS

        return SUBCOMMANDS[sub](cfg)

    return run


def _cache(sub: str) -> Callable[[DictConfig, list[str]], int]:
    def run(cfg: DictConfig, args: list[str]) -> int:
        from gdwm.housekeeping import SUBCOMMANDS, HousekeepingError, UsageError

        try:
            return SUBCOMMANDS[sub](cfg, args)
        except UsageError as e:
            err_console.print(f"gdwm cache {sub}: {e}", markup=False)
            return 2
        except HousekeepingError as e:
            err_console.print(f"gdwm cache {sub}: {e}", markup=False)
            return 1

    return run


def _config_show(cfg: DictConfig, _args: list[str]) -> int:
    shown = redact_config(OmegaConf.to_container(cfg, resolve=False))  # credentials in URIs masked
    console.print(OmegaConf.to_yaml(shown), end="", markup=False)
    return 0


COMMANDS: dict[str, dict[str, Command]] = {
    "data": {  # plugins add the commands that build their datasets (a mapping in entry-point group gdwm.commands)
        "info": Command(_data_info, "summarise the dataset selected by data=... (scenes, frames, QA, bytes)"),
    },
    "config": {
        "show": Command(_config_show, "print the resolved config"),
    },
    "run": {
        "": Command(
            _run,
            "run the pipeline DAG (targets=[...], pipeline=..., seeds=[0,1,2] for a trial per seed, --dry-run prints "
            "the plan)",
            flags=("--dry-run",),
        ),
    },
    "status": {
        "": Command(_status, "list recent MLflow runs of the configured store"),
    },
    "sweep": {
        "": Command(
            _sweep,
            "run an ablation table: sweep=NAME (conf/sweep/), overrides for every trial, seeds=[0,1,2] for a trial "
            "per seed; shared stages run once; --dry-run prints trials x stages (cached / shared / to run) and the "
            "capacity plan on the cluster (--durations=FILE: measured seconds per task, JSON stage -> seconds)",
            flags=("--dry-run",),
            options=("--durations",),
        ),
    },
    "regress": {
        "": Command(
            _regress,
            "benchmark regression: benchmark=NAME (conf/benchmark/, default nightly) vs its baseline; exit 0 ok, "
            "1 regression, 2 error; --set-baseline records this run as the baseline; evaluation targets and stages "
            "whose code changed recompute, --fresh recomputes every stage",
            defaults=["benchmark=nightly"],
            flags=("--set-baseline", "--fresh"),
        ),
    },
    "compare": {
        "": Command(
            _compare,
            'comparison table + HTML report of runs: args.sweep=NAME | args.runs=[ID,...] | args.filter="..." '
            "(default: all), compare=LAYOUT (a conf/compare/ option; the default is conf/args/compare.yaml's), "
            "args.baseline=ROW, args.out=DIR, args.formats=[...]; cells carry mean ± std over seeds or a bootstrap CI, "
            "marks need a significant difference: args.alpha=0.05, args.confidence=0.95, args.resamples=1000",
            defaults=["args=compare"],
        ),
    },
    "reproduce": {
        "": Command(
            _reproduce,
            "run a recorded trial, row, gdwm run or sweep again from scratch in a fresh workdir (RUN_ID [workdir=DIR] "
            "[args.store=WORKDIR|URI]) and say per metric and cache entry whether it came out equal, with what differs "
            "in the environment; exit 0 reproduced, 1 not, 2 bad input",
            defaults=["args=reproduce"],
            positional="args.run",
        ),
    },
    "ui": {
        "": Command(_ui, "serve the MLflow UI of the configured store (ui.host=127.0.0.1, ui.port=5000)"),
    },
    "zoo": {
        sub: Command(_zoo(sub), text, defaults=["args=zoo"])
        for sub, text in (
            ("list", "registered components: versions, variants, aliases, key metrics [args.name=NAME]"),
            ("show", "one version's tags, source and files: args.name=NAME [args.version=N|@ALIAS]"),
            ("promote", "set an alias: args.name=NAME args.version=N|@ALIAS [args.alias=champion]"),
            ("load", "download a version's files: args.name=NAME [args.version=N|@ALIAS] [args.out=DIR]"),
        )
    },
    "cache": {
        "ls": Command(
            _cache("ls"),
            "entries, size, last use, runs and zoo versions per stage; args.stage=NAME lists one stage's entries",
            defaults=["args=cache"],
        ),
        "gc": Command(
            _cache("gc"),
            "delete entries: --keep-last N (per stage and scene), --older-than AGE (30d; s/m/h/d/w), --max-size SIZE "
            "(50GB, 50GiB; least recently used first), --dry-run; never an entry a zoo alias, a regression baseline "
            "or a running run references, nor one used within args.grace=1h",
            defaults=["args=cache"],
            flags=("--dry-run",),
            options=("--keep-last", "--older-than", "--max-size"),
        ),
        "invalidate": Command(
            _cache("invalidate"),
            "remove one entry and its training checkpoints: args.stage=NAME args.key=PREFIX (>= 8 hex characters)",
            defaults=["args=cache"],
        ),
    },
}


COMMAND_GROUP = "gdwm.commands"
"""Entry-point group of plugin commands. ``name = "module:function"``: the command ``gdwm <name>``,
``function(cfg, argv) -> int``; its arguments come from ``conf/args/<name>.yaml`` (selected as ``args=<name>``), its
help from its docstring. ``name = "module:MAPPING"``: subcommands ``gdwm <name> <sub>``, a ``{sub: Command}`` mapping
(a built-in command such as ``data`` lists them before its own)."""


def _plugin_command(fn_path: str, name: str) -> Command:
    def run(cfg: DictConfig, argv: list[str]) -> int | None:
        return get_method(fn_path)(cfg, argv)

    return Command(run, "", defaults=[f"args={name}"])


@cache
def _load_plugin_commands() -> None:
    """Add the plugins' commands to COMMANDS; one whose module fails to import is listed with the error (running it
    repeats it), not fatal to the other commands."""
    for ep in sorted(entry_points(group=COMMAND_GROUP), key=lambda e: e.name):
        try:
            target = ep.load()
        except Exception as e:  # a broken plugin must not take the whole CLI down
            target = e
        if isinstance(target, Mapping):
            _add_subcommands(ep.name, ep.value, target)
            continue
        if ep.name in COMMANDS:
            raise ConfigError(f"plugin command '{ep.name}' ({ep.value}) clashes with a built-in command")
        cmd = _plugin_command(ep.value.replace(":", "."), ep.name)
        cmd.help = f"(plugin failed to load: {target!r})" if isinstance(target, Exception) else _first_doc_line(target)
        COMMANDS[ep.name] = {"": cmd}


def _add_subcommands(name: str, value: str, subs: Mapping[str, Command]) -> None:
    """A plugin's subcommands of ``gdwm <name>``, before the built-in ones of that command (if it has any)."""
    builtin = COMMANDS.get(name, {})
    if "" in builtin:
        raise ConfigError(f"plugin subcommands '{name}' ({value}): 'gdwm {name}' is a built-in command without any")
    for sub, cmd in subs.items():
        if sub in builtin:
            raise ConfigError(f"plugin subcommand '{name} {sub}' ({value}) clashes with a built-in subcommand")
        if not sub or not isinstance(cmd, Command):
            raise ConfigError(f"plugin subcommand '{name} {sub}' ({value}): expected a gdwm.cli.Command under a name")
    COMMANDS[name] = {**subs, **builtin}


def _first_doc_line(fn: object) -> str:
    doc = (getattr(fn, "__doc__", None) or "").strip()
    return doc.splitlines()[0] if doc else ""


def _groups_help() -> str:
    lines = ["config groups (pick with GROUP=OPTION):"]
    for g in MAIN_GROUPS:
        try:
            opts = ", ".join(group_options(g))
        except ConfigError:
            opts = "?"
        lines.append(f"  {g:<10} {opts}")
    lines.append("  stage/<name>, model/<name>: one group per stage and per model component (gdwm config show)")
    lines.append("common overrides: workdir=DIR (default ./gdwm-work), source=DIR, overwrite=true, data.KEY=VALUE")
    return "\n".join(lines)


def usage(command: str | None = None) -> str:
    if command is None:
        lines = ["usage: gdwm <command> [subcommand] [overrides...]", "", "commands:"]
        for name, subs in COMMANDS.items():
            for sub, c in subs.items():
                lines.append(f"  {(name + ' ' + sub).strip():<26} {c.help}")
    elif "" in COMMANDS[command]:
        c = COMMANDS[command][""]
        flags = " ".join(f"[{f}]" for f in c.flags)
        lines = [f"usage: gdwm {command} {flags + ' ' if flags else ''}[overrides...]", "", c.help]
    else:
        lines = [f"usage: gdwm {command} <subcommand> [overrides...]", "", "subcommands:"]
        for sub, c in COMMANDS[command].items():
            lines.append(f"  {sub:<20} {c.help}")
    return "\n".join([*lines, "", _groups_help()])


def _user_sets_group(overrides: list[str], group: str) -> bool:
    return any(o.split("=", 1)[0].lstrip("+~") == group for o in overrides if "=" in o)


def _join_options(args: list[str], options: tuple[str, ...]) -> tuple[list[str], str | None]:
    """``--opt VALUE`` as ``--opt=VALUE``; the name of an option left without a value (followed by nothing, a flag or
    an override KEY=VALUE), if any."""
    out, i = [], 0
    while i < len(args):
        if args[i] in options:
            if i + 1 == len(args) or args[i + 1].startswith("--") or "=" in args[i + 1]:
                return out, args[i]
            out.append(f"{args[i]}={args[i + 1]}")
            i += 2
        else:
            out.append(args[i])
            i += 1
    return out, None


def _terminated(signum: int, _frame) -> None:
    raise SystemExit(128 + signum)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    _load_plugin_commands()
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(usage())
        return 0 if argv else 2
    command, rest = argv[0], argv[1:]
    if command not in COMMANDS:
        err_console.print(f"gdwm: unknown command '{command}'; commands: {', '.join(COMMANDS)}", markup=False)
        return 2
    single = "" in COMMANDS[command]
    if (not rest and not single) or (rest and rest[0] in ("-h", "--help")):
        print(usage(command))
        return 0 if rest else 2
    sub, overrides = ("", rest) if single else (rest[0], rest[1:])
    if sub not in COMMANDS[command]:
        err_console.print(
            f"gdwm {command}: unknown subcommand '{sub}'; subcommands: {', '.join(COMMANDS[command])}", markup=False
        )
        return 2
    spec = COMMANDS[command][sub]
    if spec.positional and overrides and "=" not in overrides[0] and not overrides[0].startswith("-"):
        overrides = [f"{spec.positional}={overrides[0]}", *overrides[1:]]
    if any(o in ("-h", "--help") for o in overrides):
        head = usage(command) if not sub else f"usage: gdwm {command} {sub} [overrides...]\n\n{spec.help}"
        print(f"{head}\n\n{_groups_help()}")
        return 0
    if spec.options:
        overrides, missing = _join_options(overrides, spec.options)
        if missing:
            err_console.print(
                f"gdwm {command} {sub}: {missing} needs a value ({missing} VALUE or {missing}=VALUE)", markup=False
            )
            return 2
    flags = [
        o for o in overrides if o.startswith("--") and o not in spec.flags and o.split("=", 1)[0] not in spec.options
    ]
    if flags:
        err_console.print(
            f"gdwm {command} {sub}: unknown flag(s) {flags}; settings are overrides KEY=VALUE", markup=False
        )
        return 2
    defaults = [d for d in spec.defaults if not _user_sets_group(overrides, d.split("=", 1)[0])]
    try:
        cfg = load_config([*defaults, *(o for o in overrides if not o.startswith("--"))])
    except ConfigError as e:
        err_console.print(f"gdwm: config error: {e}", markup=False)
        return 2
    name = f"{command} {sub}".strip()
    main_thread = threading.current_thread() is threading.main_thread()
    # SIGTERM unwinds like Ctrl-C: temp directories and open runs are cleaned up on the way out (exit 143)
    previous = signal.signal(signal.SIGTERM, _terminated) if main_thread else None
    try:
        return int(spec.run(cfg, overrides) or 0)
    except Exception as e:
        # One line naming the file, scene, key, stage or actor (gdwm.errors); GDWM_DEBUG=1 shows the traceback.
        if os.environ.get("GDWM_DEBUG"):
            raise
        err_console.print(f"gdwm {name}: {redact(one_line(e))}", markup=False)
        return 1
    except KeyboardInterrupt:
        err_console.print(f"gdwm {name}: interrupted", markup=False)
        return 130
    except SystemExit as e:
        if e.code == 128 + signal.SIGTERM:
            err_console.print(f"gdwm {name}: terminated (SIGTERM); temp directories removed, runs ended", markup=False)
        raise
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
