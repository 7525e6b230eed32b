"""The understanding suites (NuInteract, NuInstruct, OmniDrive) of a table of predictions, named as in README: Stages.

Rows are dicts (or a pyarrow Table) with ``task``, ``category``, ``answer`` (reference) and ``prediction``; their
order is the ranking of grounding answers for mAP. Which rows feed which metric is a ``SuiteMapping``
(``conf/stage/evaluate_qa/suites``: ``proxy`` for synthetic data, ``nuinteract``, ``nuinstruct``, ``omnidrive`` for
the benchmarks' imported records); the suites it lists as ``proxy`` are scored on rows that stand in for that
benchmark's data. NuInstruct's metrics follow its own protocol on its records (``nuinstruct_protocol:
per_subtask``, ``pipelines.evaluate.nuinstruct``) and the pooled proxy rules otherwise. Every metric is labelled:
``official`` for BLEU/ROUGE-L/CIDEr on pycocoevalcap's PTB tokens (and the aggregates of official metrics only),
``approximate`` for the rest (no benchmark publishes code for its grounding, planning, regression, classification or
risk metrics) and for text metrics on the fallback tokenizer.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Callable, Collection, Iterable, Sequence
from dataclasses import asdict, dataclass, field
from fnmatch import fnmatchcase
from typing import Any

from gdwm.api import mean_of_printed
from pipelines.evaluate import nuinstruct
from pipelines.evaluate.config import DecisionMatch, NuInstructProtocol, Suite, SuiteMapping
from pipelines.evaluate.grounding import Scored, score_2d, score_3d
from pipelines.evaluate.planning import decision_accuracy, regression_mae
from pipelines.evaluate.text import (
    APPROXIMATE,
    FALLBACK_PROTOCOL,
    OFFICIAL,
    PTB_PROTOCOL,
    Tokenizer,
    default_tokenizer,
    label,
    text_scores,
    tokenize_all,
    warn_fallback,
)

__all__ = ["AGGREGATES", "PROTOCOL", "SuiteMapping", "SuiteResult", "score_predictions", "score_table"]

REQUIRED_COLUMNS = ("task", "category", "answer", "prediction")
NUINTERACT_TEN = (
    "nuinteract/rdp_bleu",
    "nuinteract/rdp_rouge_l",
    "nuinteract/rdp_cider",
    "nuinteract/vg2d_map",
    "nuinteract/vg2d_f1",
    "nuinteract/vg2d_miou",
    "nuinteract/vg3d_pr",
    "nuinteract/vg3d_map",
    "nuinteract/vg3d_f1",
    "nuinteract/plan_acc",
)
"""The metrics whose mean is ``nuinteract/avg``."""

_BLEU = "BLEU-4 x100, pycocoevalcap Bleu(4) ('closest' reference length)"
_ROUGE = "ROUGE-L x100, pycocoevalcap Rouge (beta 1.2)"
_CIDER = "CIDEr x100, pycocoevalcap Cider (n 4, sigma 6, document frequencies of the scored references)"
_MAP2D = "mean over IoU 0.50:0.05:0.95 of COCO 101-point AP, one box per sample ranked by sample order, unparsed = miss"
_ACC = "exact match of the decision (text before the first '.'), malformed = wrong"
_ACC_FIRST = "exact match of the decision (the first of the decision labels the text names), malformed = wrong"
_PER_SUBTASK = "mean over its subtasks (row category) of "
NUINSTRUCT_PER_SUBTASK = {
    "nuinstruct/mae": _PER_SUBTASK + "the MAE of the answers' (x, y) vectors (mean of |dx|, |dy|) or first numbers, "
    "answers' unit; unparsed predictions left out and counted (pipelines.evaluate.nuinstruct)",
    "nuinstruct/acc": _PER_SUBTASK + "the accuracy: equal (class, camera) sets where the answer names objects, else "
    "equal normalised text; malformed = wrong",
    "nuinstruct/map": _PER_SUBTASK + "the mean per-sample AP of the answers' ranked <class>[camera,x1,y1,x2,y2] "
    "objects (same class and camera, IoU 0.50:0.05:0.95, COCO 101-point); samples naming no object on either side not "
    "scored",
    "nuinstruct/bleu": _PER_SUBTASK + "BLEU-4 x100, pycocoevalcap Bleu(4) ('closest' reference length)",
}
"""``nuinstruct_protocol: per_subtask`` (NuInstruct's Table 2; VGGDrive's Average*)."""
PROTOCOL = {
    "nuinteract/rdp_bleu": _BLEU,
    "nuinteract/rdp_rouge_l": _ROUGE,
    "nuinteract/rdp_cider": _CIDER,
    "nuinteract/vg2d_map": _MAP2D,
    "nuinteract/vg2d_f1": "F1 at IoU >= 0.5: precision over parsed boxes, recall over all samples",
    "nuinteract/vg2d_miou": "mean IoU over all samples; unparsed boxes and boxes in another camera count 0",
    "nuinteract/vg3d_pr": "precision at ego-xy centre distance < 2 m over parsed predictions",
    "nuinteract/vg3d_map": "mean over centre distances {0.5,1,2,4} m (nuScenes) of COCO 101-point AP by sample order",
    "nuinteract/vg3d_f1": "F1 at ego-xy centre distance < 2 m: precision over parsed, recall over all samples",
    "nuinteract/plan_acc": _ACC,
    "nuinteract/avg": "mean of the ten NuInteract metrics as printed (2 decimals, half up), exact in Decimal",
    "nuinstruct/mae": "MAE of the first number in the text, answers' unit; unparsed predictions left out and counted",
    "nuinstruct/acc": _ACC,
    "nuinstruct/map": _MAP2D,
    "nuinstruct/bleu": _BLEU,
    "nuinstruct/average_star": "max((acc + map + bleu - mae) / 4, 0) of the values as printed (2 decimals, half up), "
    "exact, as VGGDrive defines it",
    "omnidrive/bleu": _BLEU,
    "omnidrive/cider": _CIDER,
    "omnidrive/rouge_l": _ROUGE,
    "omnidrive/avg": "mean of omnidrive bleu, cider, rouge_l as printed (2 decimals, half up), exact in Decimal",
}
"""What every metric uses (text metrics: and the tokenizer, added when scored)."""
TEXT_METRICS = frozenset(k for k, v in PROTOCOL.items() if v in (_BLEU, _ROUGE, _CIDER))
"""Official on PTB tokens."""
PRINTED_DECIMALS = 2
"""The paper's tables print 2 decimals; its aggregates are means of the printed values."""
SUITE_TITLES = {Suite.nuinteract: "NuInteract", Suite.nuinstruct: "NuInstruct", Suite.omnidrive: "OmniDrive"}
METADATA_KEY = b"gdwm.suite_mapping"
"""Schema metadata of ``predictions.parquet``: the mapping it was scored with, so a rescoring uses the same."""


@dataclass
class SuiteResult:
    metrics: dict[str, float] = field(default_factory=dict)
    """By metric name (README: Stages); a metric without samples is absent (never 0)."""
    counts: dict[str, int] = field(default_factory=dict)
    """Samples scored per group (``nuinteract/vg2d``), with ``malformed/<group>`` (unparsed predictions, scored as
    misses) and ``bad_answer/<group>`` (unparsed references, skipped) for the parsed groups."""
    protocol: dict[str, str] = field(default_factory=dict)
    """Metric name -> "<label>: <what it used>; rows: <patterns>[; proxy: ...]" (``protocol.json``)."""
    labels: dict[str, str] = field(default_factory=dict)
    """Metric name -> ``official`` | ``approximate``."""
    proxy: dict[str, str] = field(default_factory=dict)
    """Metric name -> what stands in for the benchmark's data, for the metrics of the mapping's proxy suites."""
    tokenizer: Tokenizer | None = None
    """The text metrics' tokenizer (None: no text metric was scored)."""
    subtasks: dict[str, dict[str, float]] = field(default_factory=dict)
    """Metric name -> {subtask: value}, for the metrics that are means over subtasks (NuInstruct's protocol)."""

    def params(self) -> dict[str, str]:
        """``protocol/<metric>`` (the label) and ``proxy/<metric>`` for the stage run, where ``gdwm compare``
        reads them for the table's notes; ``text_tokenizer``."""
        out = {f"protocol/{k}": v for k, v in self.labels.items()} | {f"proxy/{k}": v for k, v in self.proxy.items()}
        return out | ({"text_tokenizer": self.tokenizer.value} if self.tokenizer else {})

    def flat(self) -> dict[str, float]:
        """Metrics and ``count/<key>`` entries, all floats, for MLflow."""
        return {**self.metrics, **{f"count/{k}": float(v) for k, v in self.counts.items()}}


def _rows(rows: Any) -> list[dict]:
    rows = rows.to_pylist() if hasattr(rows, "to_pylist") else list(rows)
    for i, r in enumerate(rows):
        missing = [c for c in REQUIRED_COLUMNS if c not in r]
        if missing:
            raise ValueError(f"score_predictions: row {i} ({r.get('sample_id', 'no sample_id')}) lacks {missing}")
    return rows


AGGREGATES = {
    "nuinteract/avg": NUINTERACT_TEN,
    "nuinstruct/average_star": ("nuinstruct/acc", "nuinstruct/map", "nuinstruct/bleu", "nuinstruct/mae"),
    "omnidrive/avg": ("omnidrive/bleu", "omnidrive/cider", "omnidrive/rouge_l"),
}
"""Metrics computed from other metrics, and what they need."""
TEXT_GROUPS = {
    "nuinteract_rdp": {"nuinteract/rdp_bleu", "nuinteract/rdp_rouge_l", "nuinteract/rdp_cider"},
    "nuinstruct_caption": {"nuinstruct/bleu"},
    "omnidrive_text": {"omnidrive/bleu", "omnidrive/cider", "omnidrive/rouge_l"},
}
"""Mapping fields whose rows are scored as text, and their metrics."""


def _selected(rows: list[dict], patterns: Sequence[str]) -> list[dict]:
    pats = tuple(patterns)
    return [r for r in rows if _matches(r["task"] or "", r["category"] or "", pats)]


@functools.lru_cache(maxsize=1 << 12)
def _matches(task: str, category: str, patterns: tuple[str, ...]) -> bool:
    """A row of this task and category is one of ``patterns``' (memoised: a bootstrap selects the same few task
    families from every resample's rows)."""
    return any(fnmatchcase(v, p) for p in patterns for v in (task, category))


def score_predictions(
    rows: Iterable[dict] | Any,
    mapping: SuiteMapping | None = None,
    wanted: Collection[str] | None = None,
    tokenizer: Tokenizer | None = None,
) -> SuiteResult:
    """Every suite's metrics of prediction ``rows`` (dicts or a pyarrow Table), ranked for mAP in the given order;
    with ``wanted``, only the groups those metrics (and the aggregates among them) need. Text metrics on
    ``tokenizer``'s tokens (default: PTB where Java is, else the fallback, with one warning)."""
    m = mapping or SuiteMapping()
    rows = _rows(rows)
    out = SuiteResult()
    need = None if wanted is None else set(wanted).union(*(AGGREGATES[a] for a in wanted if a in AGGREGATES))
    tok = Tokenizer(tokenizer) if tokenizer is not None else default_tokenizer()
    text_groups = [g for g, names in TEXT_GROUPS.items() if need is None or not need.isdisjoint(names)]
    texts = [r[c] or "" for g in text_groups for r in _selected(rows, getattr(m, g)) for c in ("answer", "prediction")]
    if texts:
        if tokenizer is None and tok is Tokenizer.fallback:
            warn_fallback()
        tokenize_all(texts, tok)  # one java call for every text group
        out.tokenizer = tok
    proxies = {Suite(p) for p in m.proxy}

    def record(name: str, lab: str, what: str, patterns: Sequence[str] | None = None) -> None:
        out.labels[name] = lab
        suite = Suite(name.split("/")[0])
        rows_note = f"; rows: {', '.join(patterns)}" if patterns else ""
        proxy_note = ""
        if suite in proxies:
            used = f"rows {', '.join(patterns)}" if patterns else "NuInteract-style task families"
            out.proxy[name] = f"{used} stand in for {SUITE_TITLES[suite]}'s own data"
            proxy_note = f"; proxy: {out.proxy[name]}"
        out.protocol[name] = f"{lab}: {what}{rows_note}{proxy_note}"

    per_subtask = m.nuinstruct_protocol == NuInstructProtocol.per_subtask

    def run(
        group: str,
        score: Callable[[list[str], list[str]], Scored | dict | None],
        names: dict[str, str],
        by_subtask: bool = False,
    ) -> None:
        if need is not None and need.isdisjoint(names.values()):
            return
        patterns = getattr(m, group.replace("/", "_"))
        sel = _selected(rows, patterns)
        if not sel:
            return
        if by_subtask:
            scored = _subtask_means(sel, score, names, out, group)
        else:
            scored = score([r["answer"] or "" for r in sel], [r["prediction"] or "" for r in sel])
        if isinstance(scored, Scored):
            out.counts |= {
                group: scored.samples,
                f"malformed/{group}": scored.malformed,
                f"bad_answer/{group}": scored.bad_answers,
            }
            scored = scored.metrics
        else:
            out.counts[group] = len(sel)
        for key, name in names.items():
            if key in scored:
                out.metrics[name] = scored[key]
                what = NUINSTRUCT_PER_SUBTASK[name] if by_subtask else PROTOCOL[name]
                if what == _ACC and m.decision_match == DecisionMatch.first:
                    what = _ACC_FIRST
                if name in TEXT_METRICS:
                    what += f" on {PTB_PROTOCOL if tok is Tokenizer.ptb else FALLBACK_PROTOCOL} tokens"
                lab = label(tok) if name in TEXT_METRICS else APPROXIMATE
                record(name, lab, what, patterns)

    def accuracy(answers: Sequence[str], predictions: Sequence[str]) -> Scored:
        return decision_accuracy(answers, predictions, m.decision_labels, m.decision_match)

    def text(answers: Sequence[str], predictions: Sequence[str]) -> dict[str, float] | None:
        return text_scores(answers, predictions, tok)

    run(
        "nuinteract/rdp",
        text,
        {"bleu": "nuinteract/rdp_bleu", "rouge_l": "nuinteract/rdp_rouge_l", "cider": "nuinteract/rdp_cider"},
    )
    run(
        "nuinteract/vg2d",
        score_2d,
        {"map": "nuinteract/vg2d_map", "f1": "nuinteract/vg2d_f1", "miou": "nuinteract/vg2d_miou"},
    )
    run(
        "nuinteract/vg3d",
        score_3d,
        {"precision": "nuinteract/vg3d_pr", "map": "nuinteract/vg3d_map", "f1": "nuinteract/vg3d_f1"},
    )
    run("nuinteract/plan", accuracy, {"acc": "nuinteract/plan_acc"})
    if per_subtask:
        run("nuinstruct/regression", nuinstruct.regression_scores, {"mae": "nuinstruct/mae"}, by_subtask=True)
        run("nuinstruct/classification", nuinstruct.classification_scores, {"acc": "nuinstruct/acc"}, by_subtask=True)
        run("nuinstruct/detection", nuinstruct.risk_scores, {"map": "nuinstruct/map"}, by_subtask=True)
        run("nuinstruct/caption", text, {"bleu": "nuinstruct/bleu"}, by_subtask=True)
    else:
        run("nuinstruct/regression", regression_mae, {"mae": "nuinstruct/mae"})
        run("nuinstruct/classification", accuracy, {"acc": "nuinstruct/acc"})
        run("nuinstruct/detection", score_2d, {"map": "nuinstruct/map"})
        run("nuinstruct/caption", text, {"bleu": "nuinstruct/bleu"})
    run("omnidrive/text", text, {"bleu": "omnidrive/bleu", "cider": "omnidrive/cider", "rouge_l": "omnidrive/rouge_l"})

    def aggregate(name: str, parts: Sequence[str], signs: Sequence[int] | None = None, floor: float | None = None):
        if all(p in out.metrics for p in parts):
            values = [out.metrics[p] * (signs[i] if signs else 1) for i, p in enumerate(parts)]
            mean = mean_of_printed(values, PRINTED_DECIMALS)
            out.metrics[name] = mean if floor is None else max(mean, floor)
            official = all(out.labels[p] == OFFICIAL for p in parts)
            record(name, OFFICIAL if official else APPROXIMATE, PROTOCOL[name])

    aggregate("nuinteract/avg", AGGREGATES["nuinteract/avg"])
    # VGGDrive's Average*: max((acc + map + bleu - mae) / 4, 0)
    aggregate("nuinstruct/average_star", AGGREGATES["nuinstruct/average_star"], (1, 1, 1, -1), floor=0.0)
    aggregate("omnidrive/avg", AGGREGATES["omnidrive/avg"])
    return out


def _subtask_means(sel: list[dict], score: Callable, names: dict[str, str], out: SuiteResult, group: str) -> Scored:
    """One group's metric as the mean over its subtasks (NuInstruct's protocol): the subtasks' values go to
    ``out.subtasks``, their sample counts are summed (``empty/<group>``: risk samples with nothing to score)."""
    ((key, name),) = names.items()
    mean, results = nuinstruct.per_subtask(sel, score, key)
    total = Scored({} if mean is None else {key: mean}, 0)
    for sub, r in results.items():
        if isinstance(r, Scored):
            total.samples += r.samples
            total.malformed += r.malformed
            total.bad_answers += r.bad_answers
            if isinstance(r, nuinstruct.RiskScored):
                out.counts[f"empty/{group}"] = out.counts.get(f"empty/{group}", 0) + r.empty
            value = r.metrics.get(key)
        else:  # text scores: every row counts
            total.samples += sum(1 for row in sel if (row["category"] or "") == sub)
            value = (r or {}).get(key)
        if value is not None:
            out.subtasks.setdefault(name, {})[sub] = value
    return total


def with_mapping(table: Any, mapping: SuiteMapping) -> Any:
    """``table`` (pyarrow) carrying ``mapping`` in its schema metadata, for ``score_table``."""
    meta = dict(table.schema.metadata or {}) | {METADATA_KEY: json.dumps(asdict(mapping)).encode()}
    return table.replace_schema_metadata(meta)


def mapping_of(table: Any) -> SuiteMapping | None:
    """The mapping a predictions table was scored with (``with_mapping``); None for plain rows or older tables."""
    meta = getattr(getattr(table, "schema", None), "metadata", None) or {}
    return SuiteMapping(**json.loads(meta[METADATA_KEY])) if METADATA_KEY in meta else None


def score_table(table: Any, wanted: Collection[str] | None = None) -> dict[str, float]:
    """The metrics of a ``predictions.parquet`` table (or any subset of its rows, repeats allowed): what
    ``evaluate_qa`` logs, recomputed on bootstrap resamples by ``gdwm compare`` and ``gdwm regress`` (only the
    ``wanted`` ones and what they need), with the suite mapping the table carries."""
    return score_predictions(table, mapping_of(table), wanted=wanted).metrics
