"""``gdwm <command> [subcommand] [hydra overrides...]``.

Exit codes: 0 success, 1 a command failed (the message names what), 2 usage or config error
(nothing was launched).
"""

from __future__ import annotations

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

from gdwm.config import MAIN_GROUPS, ConfigError, drop_mlflow_litter, group_options, load_config, sqlite_path
from gdwm.errors import one_line
from gdwm.phases import mark, phase
from gdwm.redact import redact, redact_config
from gdwm.term import console, err_console, verbosity


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
    from gdwm.callables import resolve_callable
    from gdwm.datasets import verification_line

    for part in resolve_callable(cfg, "data.summarizer")(Path(cfg.data.root)):  # the dataset's own lines and tables
        console.print(part)
    console.print(verification_line(Path(cfg.data.root)), markup=False)
    return 0


def _run(cfg: DictConfig, args: list[str]) -> int:
    with phase("import runner"):
        from gdwm.dag import DagError
        from gdwm.runner import PlanError, RunError, run_pipeline

    try:
        # `gdwm run` has no command defaults: its config is composed from the user's overrides alone, and so is each
        # seed's (seeds=[...])
        summary = run_pipeline(cfg, [a for a in args if not a.startswith("--")], dry_run="--dry-run" in args,
                               verbosity=verbosity(args))  # fmt: skip
    except (DagError, PlanError) as e:
        err_console.print(f"gdwm run: {'pipeline error: ' if isinstance(e, DagError) else ''}{e}", markup=False)
        return 2
    except RunError as e:
        err_console.print(f"gdwm run: {e}", markup=False)
        return 1
    _say_failures("gdwm run", summary)
    return 0 if summary.ok else 1


def _say_failures(command: str, summary) -> None:
    """One line per failed stage execution (its cause names the traceback file), and how many stages it blocked."""
    seen: set[str] = set()
    for t in summary.trials:
        for msg in t.failed.values():
            if msg not in seen:
                seen.add(msg)
                blocked = len({s for x in summary.trials for s in x.blocked})
                where = f"trial '{t.trial.name}': " if len(summary.trials) > 1 else ""
                err_console.print(f"{command}: {where}{msg}" + (f"; {blocked} stage(s) downstream blocked" if
                                  blocked and len(summary.trials) == 1 else ""), markup=False)  # fmt: skip


def _status(cfg: DictConfig, _args: list[str]) -> int:
    from gdwm.status import status

    return status(cfg)


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
    console.print(f"dashboard: gdwm ui{work}  ->  http://{cfg.ui.host}:{cfg.ui.port}/ (MLflow's UI: gdwm ui --mlflow)")
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


def _ui(cfg: DictConfig, args: list[str]) -> int:
    """gdwm's dashboard on the configured store (``gdwm.ui``) until Ctrl-C or SIGTERM (exit 0)."""
    from gdwm.errors import CommandError
    from gdwm.ui.serve import serve

    try:
        return serve(cfg, args)
    except CommandError as e:  # a busy port, a store that cannot be read: the one line says which
        err_console.print(f"gdwm ui: {e}", markup=False)
        return 1


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
            "the plan; --quiet: failures only, --verbose: every stage start and scene)",
            flags=("--dry-run", "--quiet", "--verbose"),
        ),
    },
    "status": {
        "": Command(
            _status,
            "sweeps (trials done / total, state, duration, best row, last regression verdict), runs and regressions "
            "of the configured store: args.sweep=NAME (its rows), args.state=running|done|failed|killed, args.limit=N",
            defaults=["args=status"],
        ),
    },
    "sweep": {
        "": Command(
            _sweep,
            "run an ablation table: sweep=NAME (conf/sweep/), overrides for every trial, seeds=[0,1,2] for a trial "
            "per seed; shared stages run once; --dry-run prints trials x stages (cached / shared / to run) and the "
            "capacity plan on the cluster (--durations=FILE: measured seconds per task, JSON stage -> seconds); "
            "--quiet / --verbose",
            flags=("--dry-run", "--quiet", "--verbose"),
            options=("--durations",),
        ),
    },
    "regress": {
        "": Command(
            _regress,
            "benchmark regression: benchmark=NAME (conf/benchmark/, default nightly) vs its baseline; exit 0 ok, "
            "1 regression, 2 error; --set-baseline records this run as the baseline; evaluation targets and stages "
            "whose code changed recompute, --fresh recomputes every stage; --dry-run prints the plan and the baseline "
            "without running; --quiet / --verbose",
            defaults=["benchmark=nightly"],
            flags=("--set-baseline", "--fresh", "--dry-run", "--quiet", "--verbose"),
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
        "": Command(
            _ui,
            "gdwm's dashboard of the configured store: launches, live sweeps (trials x stages, table, plots, "
            "downloads), trials, regressions, the zoo (--port N, 0 = a free one; --host H, default 127.0.0.1; "
            "--mlflow also serves MLflow's own UI on ui.mlflow_port)",
            flags=("--mlflow",),
            options=("--port", "--host"),
        ),
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


def _follow_workdir(cfg: DictConfig) -> None:
    """A workdir copied or moved since its last command: its store's artifact locations point at it again before
    any command reads or writes them (``gdwm.tracking.relocate``)."""
    uri = OmegaConf.select(cfg, "tracking.uri", default=None)
    location = OmegaConf.select(cfg, "tracking.artifact_location", default=None)
    db = sqlite_path(str(uri)) if uri else None
    if db is None or not location or not Path(db).is_file():
        return
    from gdwm.tracking.relocate import relocate_store
    from gdwm.tracking.storelock import StoreLock, StoreLockTimeout

    timeout = OmegaConf.select(cfg, "tracking.lock_timeout_s", default=None)
    try:
        with StoreLock(db, *([float(timeout)] if timeout else [])):  # the store's one-writer lock (tracking.backend)
            relocate_store(str(uri), str(location))
    except StoreLockTimeout as e:  # one line naming the lock and its holder, as the backend says it
        from gdwm.tracking.backend import TrackingError  # here: it imports Ray, which most commands never need

        raise TrackingError(str(e)) from None


def _terminated(signum: int, _frame) -> None:
    raise SystemExit(128 + signum)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    mark("main")  # from the process' start to here: the interpreter and gdwm.cli's imports
    with phase("plugins"):
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
        with phase("compose"):
            cfg = load_config([*defaults, *(o for o in overrides if not o.startswith("--"))])
    except ConfigError as e:
        err_console.print(f"gdwm: config error: {e}", markup=False)
        return 2
    name = f"{command} {sub}".strip()
    main_thread = threading.current_thread() is threading.main_thread()
    # SIGTERM unwinds like Ctrl-C: temp directories and open runs are cleaned up on the way out (exit 143)
    previous = signal.signal(signal.SIGTERM, _terminated) if main_thread else None
    try:
        with phase("relocate"):
            _follow_workdir(cfg)
        return int(spec.run(cfg, overrides) or 0)
    except ConfigError as e:  # found once the command looked closer (a function the config names, say): exit 2
        err_console.print(f"gdwm: config error: {e}", markup=False)
        return 2
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
        drop_mlflow_litter(str(cfg.tracking.uri))
        mark("return")


if __name__ == "__main__":
    sys.exit(main())
