"""The words under every table: what the marks mean and which rule and test gave them in which column, what the cells
and their uncertainty are, which rows are reported (copied from papers) and which cells lack seeds.

The key to the marks depends on where the table goes: ``Bold: best; underlined: second.`` where the format can
typeset (a terminal, Markdown, LaTeX, HTML, CSV's ``mark`` column), ``* best; † second`` where it cannot (a log).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from gdwm.compare.marks import BEST, CORRECTION_NAMES, SECOND, Rule
from gdwm.compare.stats import Analysis, RowInput, Settings

KEY = "Bold: best; underlined: second."
CHARS = {BEST: "*", SECOND: "†"}
"""Marks printed as characters after the value where bold and underline do not survive (a log file, a pipe)."""
KEY_CHARS = f"{CHARS[BEST]} best; {CHARS[SECOND]} second (after the value: bold and underline do not survive a log)."


def _count(ns: Sequence[int], noun: str) -> str:
    lo, hi = min(ns), max(ns)
    return f"{lo} {noun}" + ("" if hi == 1 else "s") if lo == hi else f"{lo}–{hi} {noun}s"


def _names(names: Sequence[str]) -> str:
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} and {names[-1]}"


def _tests(a: Analysis, settings: Settings, used: set[str]) -> str:
    parts = []
    if used & {"bootstrap", "bootstrap+welch"}:
        samples = " and ".join(
            f"{b.n_samples}" + (f" ({b.stage})" if len(a.bootstraps) > 1 else "") for b in a.bootstraps
        )
        seeds = _count([n for b in a.bootstraps for n in b.seeds], "seed")
        parts.append(
            f"a paired bootstrap over {samples} held-out samples, {seeds}: two-sided p from the "
            f"{settings.n_resamples} resampled differences"
        )
    if "bootstrap+welch" in used:
        parts.append("and, between rows of >= 2 seeds, Welch's t-test over the seeds: the larger p counts")
    if "welch" in used:
        parts.append(f"{'else ' if parts else ''}Welch's t-test over seeds")
    if "untested" in used:
        parts.append("pairs with neither per-sample data nor 2 seeds on both sides cannot be told apart")
    return "; ".join(parts)


def marks_sentence(
    rows: Sequence[RowInput], a: Analysis, settings: Settings, names: Mapping[str, str], rule: Rule
) -> str:
    """Which rule marked which column, how significance was decided, and how reported rows take part."""
    marked = [m for m, d in a.decisions.items() if d.marks]
    if not marked:
        return ""
    sig = [m for m in marked if a.decisions[m].rule is Rule.significance]
    by_value = [m for m in marked if a.decisions[m].rule is Rule.value]
    reported = any(r.reported for r in rows)
    out = []
    if sig:
        used = set().union(*(a.decisions[m].tests for m in sig))
        pairs = [len(a.decisions[m].pvalues) for m in sig if a.decisions[m].pvalues]
        correction = CORRECTION_NAMES[settings.correction]
        family = f"{correction} over each column's {_count(pairs, 'pair')}" if pairs else correction
        where = "every column" if not by_value else _names([names[m] for m in sig])
        out.append(
            f"Marks by significance in {where}: in value order, each row shares the mark of the row that opened it "
            f"unless significantly worse than that row, and then opens the next mark; no row outranks a better value "
            f"({_tests(a, settings, used)}; {family}; α = {settings.alpha:g})."
        )
    if by_value:
        if rule is Rule.value:
            why = "compare.marks=value"
        elif all(r.reported for i, r in enumerate(rows) if any((i, m) in a.cells for m in by_value) and not r.failed):
            why = "reported values only"
        else:
            why = "some row has neither per-sample data nor 2 seeds"
        where = "every column" if not sig else _names([names[m] for m in by_value])
        out.append(f"Marks by value in {where} ({why}); rows that print the same share.")
    if reported and sig:
        out.append("Reported rows take part by value only: a test never extends a mark to or past them.")
    return " ".join(out)


def cells_sentence(rows: Sequence[RowInput], a: Analysis, settings: Settings) -> str:
    """What a cell shows: mean ± std over seeds, a value with its bootstrap interval, or a value alone."""
    live = {k: c for k, c in a.cells.items() if not rows[k[0]].failed}
    mine = {k: c for k, c in live.items() if not rows[k[0]].reported}
    pct = f"{settings.confidence * 100:g}%"
    fell_back = any(b.fell_back for b in a.bootstraps)
    method = settings.method + (", percentile where it was degenerate" if fell_back else "")
    kinds = []
    if any(c.n >= 2 for c in mine.values()):
        kinds.append("mean ± std over n seeds")
    if any(c.n == 1 and c.interval == "bootstrap" for c in mine.values()):
        kinds.append(f"one seed: value [{pct} bootstrap CI over held-out samples ({method})]")
    if any(c.n == 1 and c.interval is None for c in mine.values()):
        kinds.append("one seed without per-sample data: the value alone")
    if len(mine) < len(live):
        kinds.append("reported rows (with a source): the published value")
    return f"Cells: {'; '.join(kinds)}." if kinds else ""


def legend(
    rows: Sequence[RowInput], a: Analysis, settings: Settings, names: Mapping[str, str], rule: Rule = Rule.auto
) -> str:
    """Everything but the key to the marks (which depends on the output: ``KEY`` or ``KEY_CHARS``)."""
    out = [marks_sentence(rows, a, settings, names, rule), cells_sentence(rows, a, settings)]
    live = {k: c for k, c in a.cells.items() if not rows[k[0]].failed and not rows[k[0]].reported}
    short = sorted({rows[i].planned for (i, _), c in live.items() if c.n < rows[i].planned})
    if short:
        planned = str(short[0]) if len(short) == 1 else "the planned"
        out.append(f"(n=k): k of {planned} seeds finished.")
    if a.seeded and a.marks and any(c.n < 2 for c in live.values()):
        out.append(
            "Cells of one seed take no mark" + (" (reported rows aside)." if any(r.reported for r in rows) else ".")
        )
    for b in a.bootstraps:
        if b.n_samples < b.largest:
            out.append(
                f"{b.stage}: rows are compared on the {b.n_samples} sample ids they all share (of up to {b.largest})."
            )
    return " ".join(x for x in out if x)
