"""``python -m benchmarks [NAME ...] [--quick]``: run benchmarks, print a table, write JSON."""

from __future__ import annotations

import argparse
import json
import sys
from importlib.metadata import EntryPoint, entry_points
from pathlib import Path

from rich.table import Table

from gdwm.regress import BENCHMARK_GROUP
from gdwm.term import console

RESULTS = Path(__file__).resolve().parent / "results"


def discover() -> dict[str, EntryPoint]:
    """The registered benchmarks by name (pyproject.toml, entry-point group ``gdwm.benchmarks``: ``module:run``)."""
    return {ep.name: ep for ep in sorted(entry_points(group=BENCHMARK_GROUP), key=lambda e: e.name)}


def main(argv: list[str] | None = None) -> int:
    registered = discover()
    names = list(registered)
    ap = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__)
    ap.add_argument("names", nargs="*", help=f"benchmarks to run (default all): {', '.join(names)}")
    ap.add_argument("--quick", action="store_true", help="fewer repeats and smaller sizes (smoke run)")
    args = ap.parse_args(argv)
    unknown = sorted(set(args.names) - set(names))
    if unknown:
        ap.error(f"unknown benchmark(s) {unknown}; available: {names}")
    results = []
    for name in args.names or names:
        console.print(f"[bold]running {name}[/bold]")
        results += registered[name].load()(quick=args.quick)
    table = Table(title="gdwm benchmarks", header_style="bold")
    for col in ("benchmark", "metric", "value", "target", "verdict", "detail"):
        table.add_column(col)
    for r in results:
        verdict = {True: "[green]ok[/green]", False: "[red]MISSED[/red]", None: "-"}[r.passed]
        target = f"{r.op} {r.target:g} {r.unit}" if r.target is not None else "-"
        table.add_row(r.bench, r.metric, f"{r.value:.4g} {r.unit}", target, verdict, r.detail)
    console.print(table)
    RESULTS.mkdir(exist_ok=True)
    out = RESULTS / "latest.json"
    out.write_text(json.dumps([r.to_dict() for r in results], indent=2))
    console.print(f"results written to {out}")
    return 1 if any(r.passed is False for r in results) else 0


if __name__ == "__main__":
    sys.exit(main())
