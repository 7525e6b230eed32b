"""The consoles gdwm prints with: wide enough when piped (CI logs, tests) that tables do not wrap; text printed
through them has its credentials masked (:func:`gdwm.redact.redact`), whatever message carries a URI."""

from __future__ import annotations

import sys

from rich.console import Console
from rich.table import Table

from gdwm.redact import redact


def _width(stream) -> int | None:
    return None if stream.isatty() else 160


class RedactingConsole(Console):
    """A ``Console`` whose ``print`` masks credentials in its string arguments (tables and other renderables
    are printed as given: build them from redacted text)."""

    def print(self, *objects, **kwargs) -> None:
        super().print(*(redact(o) if isinstance(o, str) else o for o in objects), **kwargs)


console = RedactingConsole(highlight=False, width=_width(sys.stdout))
err_console = RedactingConsole(stderr=True, highlight=False, soft_wrap=True)


def _fmt_bytes(n: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{n} B"
        n /= 1024
    return f"{n} B"


def print_dataset_summary(s: dict) -> None:
    """A dataset summarizer's dict as tables: counts, bytes on disk, QA per task family and split."""
    console.print(
        f"[bold]{s['name']}[/bold] at {s['root']}  (source {s['source']}, fingerprint {s['fingerprint'][:12]})"
    )
    t = Table(show_header=True, header_style="bold")
    for col in ("scenes", "frames", "cameras", "weathers", "3D boxes", "2D boxes", "QA", "files", "on disk"):
        t.add_column(col, justify="right")
    t.add_row(
        str(s["scenes"]),
        str(s["frames"]),
        str(len(s["cameras"])),
        ",".join(s["weathers"]) or "-",
        str(s["boxes3d"]),
        str(s["boxes2d"]),
        str(s["qa_total"]),
        str(s["files"]),
        _fmt_bytes(s["bytes"]),
    )
    console.print(t)
    q = Table(title="QA per task family", show_header=True, header_style="bold")
    for task in s["qa_per_task"]:
        q.add_column(task, justify="right")
    q.add_row(*(str(v) for v in s["qa_per_task"].values()))
    console.print(q)
    splits = ", ".join(f"{k} {v}" for k, v in s["qa_per_split"].items())
    console.print(f"QA splits: {splits or '-'}")
    for line in s.get("notes", ()):  # whatever else the dataset's summarizer has to say, one line each
        console.print(line)
