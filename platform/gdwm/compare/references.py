"""Reported rows: numbers copied from papers, read from ``compare.references=FILE`` (CSV or YAML) and shown beside the
table's own rows, marked by value only (``marks``), never entering a regression's baseline.

CSV: a header ``row,paper,table,year,<metric>,...`` then one line per row; ``row`` and ``paper`` are required and the
metric columns are the layout's metric names. YAML: a list of ``{row, paper, table, year, metrics: {<metric>:
<value>}}``. A cell left empty (or ``-``, ``--``, ``–``) is missing, as in a paper's table. An aggregate column
(``mean_of`` in the layout, e.g. Avg.) may be left out: ``gdwm compare`` computes it from the printed values as it
does for every row, and warns where a published one differs.

Every error names the file, the line and the field: an unknown metric, a value that is not a finite number, a
duplicate row label, a label a row of the compared runs already has (``clashes``).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from gdwm.compare.layout import LayoutConfig
from gdwm.compare.runs import REFERENCE_KIND, Row, Source, Trial

MISSING_CELLS = frozenset({"", "-", "--", "–", "—"})
FIELDS = ("row", "paper", "table", "year")
"""Fields of a reported row besides its metrics (CSV header names, YAML keys; YAML's metrics are under ``metrics``)."""


class ReferencesError(ValueError):
    """A references file that cannot be used; the message reads ``FILE:LINE: field 'F': what is wrong``."""


@dataclass
class Reference:
    """One reported row as its file gives it."""

    label: str
    source: Source
    values: dict[str, float] = field(default_factory=dict)
    """Metric -> the published value (absent = not reported)."""
    file: str = ""
    line: int = 0
    """Where the row starts in ``file`` (1-based)."""
    lines: dict[str, int] = field(default_factory=dict)
    """Metric -> the line of its value (YAML may spread a row over lines)."""

    def where(self, name: str = "row") -> str:
        return f"{self.file}:{self.lines.get(name, self.line)}: field '{name}'"

    def row(self) -> Row:
        """The row the table shows: one trial holding the published values, no seeds, no samples."""
        trial = Trial("", None, "FINISHED", dict(self.values))
        return Row("", self.label, "FINISHED", "", dict(self.values), trials=[trial], source=self.source)


def known(layout: LayoutConfig, metric: str) -> bool:
    """A metric the layout shows: one of its columns, or one it discovers (``<discover><group>/<leaf>``)."""
    if metric in layout.columns:
        return True
    if not layout.discover or not metric.startswith(layout.discover):
        return False
    group, _, leaf = metric[len(layout.discover) :].rpartition("/")
    return bool(group) and bool(leaf)


def _number(ref: Reference, metric: str, text: str) -> float | None:
    text = text.strip()
    if text in MISSING_CELLS:
        return None
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise ReferencesError(f"{ref.where(metric)}: {text!r} is not a number (leave the cell empty or '-' if missing)")
    return value


def _metrics_of(layout: LayoutConfig) -> str:
    names = list(layout.columns) + ([f"{layout.discover}<group>/<metric>"] if layout.discover else [])
    return ", ".join(names) or "none"


def _check(ref: Reference, layout: LayoutConfig, seen: dict[str, int]) -> Reference:
    if not ref.label:
        raise ReferencesError(f"{ref.where('row')}: a row needs a label")
    if not ref.source.paper:
        raise ReferencesError(f"{ref.where('paper')}: row '{ref.label}' needs its source paper")
    if ref.label in seen:
        first = seen[ref.label]
        raise ReferencesError(f"{ref.where('row')}: duplicate row label '{ref.label}' (first on line {first})")
    seen[ref.label] = ref.line
    return ref


def _unknown(ref: Reference, metric: str, layout: LayoutConfig) -> ReferencesError:
    return ReferencesError(
        f"{ref.where(metric)}: unknown metric '{metric}' for layout '{layout.name}' "
        f"(its metrics: {_metrics_of(layout)})"
    )


def _read_csv(path: Path, layout: LayoutConfig) -> list[Reference]:
    with path.open(newline="", encoding="utf-8") as f:
        reader = csv.reader(f)
        header = [h.strip() for h in next(reader, [])]
        name = str(path)
        for h in ("row", "paper"):
            if h not in header:
                raise ReferencesError(f"{name}:1: field '{h}': the header needs a '{h}' column (header: {header})")
        probe = Reference("", Source(""), file=name, line=1)
        for h in header:
            if h not in FIELDS and not known(layout, h):
                raise _unknown(probe, h, layout)
        refs, seen = [], {}
        for cells in reader:
            if not any(c.strip() for c in cells):
                continue
            line = reader.line_num
            if len(cells) != len(header):
                raise ReferencesError(f"{name}:{line}: field 'row': {len(cells)} cells, the header has {len(header)}")
            rec = dict(zip(header, (c.strip() for c in cells), strict=True))
            source = Source(rec["paper"], rec.get("table", ""), rec.get("year", ""))
            ref = Reference(rec["row"], source, file=name, line=line)
            for metric in (h for h in header if h not in FIELDS):
                value = _number(ref, metric, rec[metric])
                if value is not None:
                    ref.values[metric] = value
            refs.append(_check(ref, layout, seen))
    return refs


def _scalar(node: yaml.Node, where: str) -> str:
    if not isinstance(node, yaml.ScalarNode):
        raise ReferencesError(f"{where}: expected a single value")
    return str(node.value)


def _read_yaml(path: Path, layout: LayoutConfig) -> list[Reference]:
    name = str(path)
    try:
        doc = yaml.compose(path.read_text(encoding="utf-8"), Loader=yaml.SafeLoader)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        line = mark.line + 1 if mark is not None else 1
        raise ReferencesError(f"{name}:{line}: field 'row': not valid YAML ({getattr(e, 'problem', e)})") from None
    if doc is None:
        return []
    if not isinstance(doc, yaml.SequenceNode):
        raise ReferencesError(f"{name}:{doc.start_mark.line + 1}: field 'row': expected a list of rows")
    refs, seen = [], {}
    for item in doc.value:
        line = item.start_mark.line + 1
        if not isinstance(item, yaml.MappingNode):
            raise ReferencesError(f"{name}:{line}: field 'row': a row is a mapping (row, paper, table, year, metrics)")
        rec: dict[str, str] = {}
        ref = Reference("", Source(""), file=name, line=line)
        metrics: list[tuple[yaml.Node, yaml.Node]] = []
        for k, v in item.value:
            key = _scalar(k, f"{name}:{k.start_mark.line + 1}: field '?'")
            ref.lines[key] = k.start_mark.line + 1
            if key == "metrics":
                if not isinstance(v, yaml.MappingNode):
                    raise ReferencesError(f"{ref.where('metrics')}: expected a mapping metric -> value")
                metrics = v.value
            elif key in FIELDS:
                rec[key] = _scalar(v, ref.where(key)).strip()
            else:
                raise ReferencesError(f"{ref.where(key)}: unknown field (a row has {', '.join(FIELDS)}, metrics)")
        ref.label = rec.get("row", "")
        ref.source = Source(rec.get("paper", ""), rec.get("table", ""), rec.get("year", ""))
        for k, v in metrics:
            metric = _scalar(k, ref.where("metrics"))
            ref.lines[metric] = k.start_mark.line + 1
            if not known(layout, metric):
                raise _unknown(ref, metric, layout)
            if metric in ref.values:
                raise ReferencesError(f"{ref.where(metric)}: given twice in row '{ref.label}'")
            value = _number(ref, metric, "" if v.tag.endswith(":null") else _scalar(v, ref.where(metric)))
            if value is not None:
                ref.values[metric] = value
        refs.append(_check(ref, layout, seen))
    return refs


def load_references(path: str | Path, layout: LayoutConfig) -> list[Reference]:
    """The reported rows of a CSV (``.csv``) or YAML (``.yaml``/``.yml``) file, checked against ``layout``."""
    p = Path(path)
    if not p.is_file():
        raise ReferencesError(f"{p}:0: field 'compare.references': no such file")
    if p.suffix.lower() == ".csv":
        return _read_csv(p, layout)
    if p.suffix.lower() in (".yaml", ".yml"):
        return _read_yaml(p, layout)
    raise ReferencesError(f"{p}:0: field 'compare.references': a references file is .csv, .yaml or .yml")


def clashes(refs: Iterable[Reference], rows: Iterable[Row], selector: str) -> None:
    """Refuse a reported row whose label a compared run's row already has (a logged reported row of the same label
    is that same row: the caller drops it)."""
    own = {r.label for r in rows if not r.reported}
    for ref in refs:
        if ref.label in own:
            raise ReferencesError(f"{ref.where('row')}: label '{ref.label}' clashes with a row of {selector}")


def merge(refs: list[Reference], rows: list[Row], selector: str) -> list[Row]:
    """The file's reported rows, then the selected rows (a reported run of the same label is replaced by the file's)."""
    clashes(refs, rows, selector)
    labels = {r.label for r in refs}
    return [r.row() for r in refs] + [r for r in rows if not (r.reported and r.label in labels)]


def log_references(
    backend, refs: Iterable[Reference], parent_run_id: str | None = None, logged: Iterable[Row] = ()
) -> list[str]:
    """Each reported row as a finished run tagged ``gdwm.kind=reference`` (under ``parent_run_id``, e.g. the sweep run,
    so that ``gdwm compare args.sweep=NAME`` shows it without the file); returns the ids of the runs it created. A
    row ``logged`` already holds (same label, source and values) is not logged again."""
    same = {(r.label, r.source, tuple(sorted(r.metrics.items()))) for r in logged if r.reported}
    ids = []
    for ref in refs:
        if (ref.label, ref.source, tuple(sorted(ref.values.items()))) in same:
            continue
        tags = {"gdwm.kind": REFERENCE_KIND, "gdwm.row": ref.label, **ref.source.tags()}
        run_id = backend.create_run(f"reference-{ref.label}", tags, parent_run_id=parent_run_id)
        backend.log_metrics(run_id, ref.values)
        backend.end_run(run_id)
        ids.append(run_id)
    return ids
