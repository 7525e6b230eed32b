"""The table as a rich table, Markdown, LaTeX (booktabs) and CSV; each carries the table's legend and notes.

Reported rows (copied from papers) come first with their ``source``; a rule separates them from the table's own
where the format has rules. Where bold and underline cannot show (a terminal table piped to a log), ``to_rich(...,
chars=True)`` prints the marks as characters after the value (``*`` best, ``†`` second) and the legend says so;
its cells wrap (``overflow="fold"``) rather than cut a label or an interval.
"""

from __future__ import annotations

import csv
import io
import re

from rich.table import Table as RichTable
from rich.text import Text

from gdwm.compare.table import BEST, SECOND, Table

_STYLE = {BEST: "bold", SECOND: "underline"}


def _cell(table: Table, i: int, metric: str) -> tuple[str, str | None]:
    return table.text(i, metric), table.marks.get((i, metric))


def to_rich(table: Table, chars: bool = False) -> RichTable:
    """Group names head the first column of their group; bold = best, underlined = second (``chars``: ``*`` and
    ``†`` after the value, for output that is not a terminal); legend and notes as caption. Cells wrap, never cut."""
    has_notes = table.has_notes  # once: it looks at every row
    lines = table.caption_lines(chars)
    caption = Text("\n".join(lines)) if lines else None  # Text: a "[" in a note is no markup
    t = RichTable(title=table.title, header_style="bold", caption=caption, caption_justify="left")
    top = "\n" if any(c.group for c in table.columns) else ""  # a first header line for the group names
    for name in table.lead_names:
        t.add_column(top + name, overflow="fold")
    seen: set[str] = set()
    for c in table.columns:
        group = c.group if c.group not in seen else ""
        seen.add(c.group)
        t.add_column((f"{group}\n" if top else "") + f"{c.header} {c.arrow}", justify="right", overflow="fold")
    if has_notes:
        t.add_column("note", style="red", overflow="fold")
    for i, r in enumerate(table.rows):
        cells = [Text(x) for x in table.lead(i)]
        for c in table.columns:
            mark = table.marks.get((i, c.metric))
            cells.append(Text(table.text(i, c.metric, chars), style="" if chars else _STYLE.get(mark, "")))
        if has_notes:
            cells.append(Text(r.note))
        t.add_row(*cells, style="dim" if r.failed else None, end_section=table.block_ends(i))
    return t


def _md_escape(s: str) -> str:
    return s.replace("|", r"\|")


def to_markdown(table: Table) -> str:
    """GitHub Markdown: ``**best**``, ``<u>second</u>``; headers read ``<group> <header> ↑``; legend and notes under
    it, a paragraph each."""
    has_notes = table.has_notes  # once: it looks at every row
    head = [*table.lead_names, *(c.label for c in table.columns)]
    head += ["note"] if has_notes else []
    lines = [f"**{_md_escape(table.title)}**", "", "| " + " | ".join(map(_md_escape, head)) + " |"]
    align = ["---"] * len(table.lead_names) + ["---:"] * len(table.columns) + ["---"] * has_notes
    lines.append("| " + " | ".join(align) + " |")
    for i, r in enumerate(table.rows):
        cells = table.lead(i)
        for c in table.columns:
            text, mark = _cell(table, i, c.metric)
            cells.append(f"**{text}**" if mark == BEST else f"<u>{text}</u>" if mark == SECOND else text)
        cells += [r.note] if has_notes else []
        lines.append("| " + " | ".join(map(_md_escape, cells)) + " |")
    for line in table.caption:
        lines += ["", _md_escape(line)]
    return "\n".join(lines) + "\n"


_TEX = {
    **{c: "\\" + c for c in "&%$#_{}"},
    "\\": r"\textbackslash{}",
    "~": r"\textasciitilde{}",
    "^": r"\textasciicircum{}",
    "–": "--",
    "↑": r"$\uparrow$",
    "↓": r"$\downarrow$",
    "±": r"$\pm$",
    "→": r"$\rightarrow$",
    "α": r"$\alpha$",
}
_TEX_RE = re.compile("|".join(map(re.escape, _TEX)))


def tex_escape(s: str) -> str:
    return _TEX_RE.sub(lambda m: _TEX[m.group()], s)


def _tex_cell(table: Table, i: int, metric: str) -> str:
    """``35.10{\\scriptsize$\\pm$1.20}``, ``35.10{\\scriptsize[33.02, 37.21]}``, then ``{\\scriptsize~(n=2)}``."""
    value, unc, count = table.parts(i, metric)
    text = tex_escape(value)
    if unc.startswith("±"):
        text += f"{{\\scriptsize$\\pm${tex_escape(unc[1:].strip())}}}"
    elif unc:
        text += f"{{\\scriptsize{tex_escape(unc)}}}"
    if count:
        text += f"{{\\scriptsize~{tex_escape(count)}}}"
    mark = table.marks.get((i, metric))
    return f"\\textbf{{{text}}}" if mark == BEST else f"\\underline{{{text}}}" if mark == SECOND else text


def to_latex(table: Table) -> str:
    """A booktabs ``tabular`` (needs booktabs); group headers as ``\\multicolumn`` over a ``\\cmidrule``; legend and
    notes as comments above it and in a ``\\caption{...}`` line (commented, to paste into the float) below."""
    has_notes = table.has_notes  # once: it looks at every row
    lead = len(table.lead_names)
    spec = "l" * lead + "c" * len(table.columns) + ("l" if has_notes else "")
    lines = [
        f"% {tex_escape(table.title)} (needs \\usepackage{{booktabs}})",
        *([f"% Legend: {table.legend}"] if table.legend else []),
        *(f"% Note: {n}" for n in table.notes),
        f"\\begin{{tabular}}{{{spec}}}",
        r"\toprule",
    ]
    if any(c.group for c in table.columns):
        cells, rules, col = [""] * lead, [], lead + 1
        for group, span in table.groups():
            cells.append(f"\\multicolumn{{{span}}}{{c}}{{{tex_escape(group)}}}" if group else "")
            cells += [""] * (0 if group else span - 1)
            if group:
                rules.append(f"\\cmidrule(lr){{{col}-{col + span - 1}}}")
            col += span
        cells += [""] if has_notes else []
        lines += [" & ".join(cells) + r" \\", "".join(rules)]
    head = ["Row", *table.lead_names[1:], *(f"{c.header} {c.arrow}" for c in table.columns)]
    head += ["Note"] if has_notes else []
    lines += [" & ".join(map(tex_escape, head)) + r" \\", r"\midrule"]
    for i, r in enumerate(table.rows):
        cells = [tex_escape(x) for x in table.lead(i)]
        cells += [_tex_cell(table, i, c.metric) for c in table.columns]
        cells += [tex_escape(r.note)] if has_notes else []
        lines.append(" & ".join(cells) + r" \\")
        if table.block_ends(i):
            lines.append(r"\midrule")
    lines += [r"\bottomrule", r"\end{tabular}"]
    if table.caption:
        lines.append(f"% \\caption{{{tex_escape(table.title)}. {tex_escape(' '.join(table.caption))}}}")
    return "\n".join(lines) + "\n"


CSV_STATS = ("std", "n", "ci_low", "ci_high", "mark")
"""Per metric, after its mean: ``<metric>/<stat>`` columns."""
SOURCE_FIELDS = ("paper", "table", "year")


def to_csv(table: Table) -> str:
    """One line per row: label, run id, status (``reported`` for a reported row), factors, the source (``paper``,
    ``table``, ``year``, when a row is reported), then per metric its mean, std, n, CI and mark (full precision;
    empty = missing), note; legend and notes as last lines starting with ``#`` (pandas: ``comment="#"``)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    metrics = [[c.metric, *(f"{c.metric}/{s}" for s in CSV_STATS)] for c in table.columns]
    source = list(SOURCE_FIELDS) if table.reported else []
    w.writerow(["row", "run_id", "status", *table.factors, *source, *(h for m in metrics for h in m), "note"])
    for i, r in enumerate(table.rows):
        factors = [r.factors.get(f, "") for f in table.factors]
        if source:
            factors += [getattr(r.source, k) for k in SOURCE_FIELDS] if r.source else [""] * len(SOURCE_FIELDS)
        values = []
        for c in table.columns:
            cell = table.cell(i, c.metric)
            if cell is None:
                values += [""] * (1 + len(CSV_STATS))
                continue
            stats = (cell.mean, cell.std, cell.n, cell.ci_low, cell.ci_high)
            values += ["" if v is None else repr(v) for v in stats] + [table.marks.get((i, c.metric), "")]
        w.writerow([r.label, r.run_id, "reported" if r.reported else r.status, *factors, *values, r.note])
    for line in table.caption:
        buf.write(f"# {line}\n")
    return buf.getvalue()
