"""The comparison table as the sweep page shows it: the same cells, intervals and marks as ``gdwm compare`` (the
``Table`` its code built; every cell's text is ``Table.parts``), laid out to read at 1280 px: the row labels stay at
the left edge, the table's key metric (a paper table's last column, its Avg.) at the right edge, and the factor and
metric groups scroll between them."""

from __future__ import annotations

from html import escape

from gdwm.compare.table import BEST, SECOND, Table


def _lead_names(table: Table) -> list[str]:
    # ``lead_names`` / ``lead`` (a reported row's source column) where the compare code has them
    return list(getattr(table, "lead_names", ["row", *table.factors]))


def _lead(table: Table, i: int) -> list[str]:
    lead = getattr(table, "lead", None)
    return list(lead(i)) if lead else [table.rows[i].label, *(table.factor(i, f) for f in table.factors)]


def cell_html(table: Table, i: int, metric: str) -> str:
    value, unc, count = table.parts(i, metric)
    mark = table.marks.get((i, metric), "")
    text = escape(value) + (f' <span class="unc">{escape(unc)}</span>' if unc else "")
    text += f' <span class="n">{escape(count)}</span>' if count else ""
    if mark == BEST:
        text = f"<strong>{text}</strong>"
    elif mark == SECOND:
        text = f"<u>{text}</u>"
    return text


def table_html(table: Table, key_metric: str | None, links: dict[str, str]) -> str:
    """``links``: row run id -> the dashboard page the row label links to."""
    lead = _lead_names(table)
    pinned = key_metric if key_metric in {c.metric for c in table.columns} else None
    cols = [c for c in table.columns if c.metric != pinned]
    end = [c for c in table.columns if c.metric == pinned]
    grouped = any(c.group for c in cols)
    span = ' rowspan="2"' if grouped else ""
    head = [f'<th class="pin-left"{span}>{escape(lead[0])}</th>']
    head += [f'<th class="factor"{span}>{escape(h)}</th>' for h in lead[1:]]
    second = []
    if grouped:
        groups: list[tuple[str, int]] = []
        for c in cols:
            if groups and groups[-1][0] == c.group:
                groups[-1] = (c.group, groups[-1][1] + 1)
            else:
                groups.append((c.group, 1))
        head += [f'<th class="group" colspan="{n}">{escape(g)}</th>' for g, n in groups]
        second = [f'<th class="metric" title="{escape(c.metric)}">{escape(c.header)} {c.arrow}</th>' for c in cols]
    else:
        head += [f'<th class="metric" title="{escape(c.metric)}">{escape(c.header)} {c.arrow}</th>' for c in cols]
    head += [f'<th class="pin-right metric"{span} title="{escape(c.metric)}">{escape(c.label)}</th>' for c in end]
    if table.has_notes:
        head.append(f'<th class="note"{span}>note</th>')
    thead = "<tr>" + "".join(head) + "</tr>" + ("<tr>" + "".join(second) + "</tr>" if second else "")
    body = []
    for i, r in enumerate(table.rows):
        lead_cells = _lead(table, i)
        href = links.get(r.run_id)
        label = f'<a href="{escape(href)}">{escape(lead_cells[0])}</a>' if href else escape(lead_cells[0])
        tds = [f'<th class="pin-left" scope="row" title="{escape(lead_cells[0])}">{label}</th>']
        tds += [f'<td class="factor">{escape(x)}</td>' for x in lead_cells[1:]]
        for c in [*cols, *end]:
            mark = table.marks.get((i, c.metric), "")
            cls = "num pin-right" if c.metric == pinned else "num"
            tds.append(
                f'<td class="{cls}" data-metric="{escape(c.metric)}" data-mark="{mark}">'
                f"{cell_html(table, i, c.metric)}</td>"
            )
        if table.has_notes:
            tds.append(f'<td class="note">{escape(r.note)}</td>')
        body.append(f'<tr class="{"failed" if r.failed else "ok"}" data-row="{escape(r.label)}">{"".join(tds)}</tr>')
    caption = "".join(f'<p class="legend">{escape(line)}</p>' for line in table.caption)
    return (
        f'<div class="tablewrap"><table class="paper" id="results"><thead>{thead}</thead>'
        f'<tbody>{"".join(body)}</tbody></table></div><div id="legend">{caption}</div>'
    )
