"""The understanding suites (NuInteract, NuInstruct, OmniDrive) of a table of predictions, named as in README: Stages.

Rows are dicts (or a pyarrow Table) with ``task``, ``category``, ``answer`` (reference) and ``prediction``; their
order is the ranking of grounding answers for mAP. Which rows feed which metric is a ``SuiteMapping``. No official
public code exists for these protocols, and our tokenizer is not PTB's, so every metric is recorded ``approximate``.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Iterable, Sequence
from dataclasses import dataclass, field
from fnmatch import fnmatchcase
from typing import Any

from pipelines.data.synth.planning import DIRECTION_DECISIONS, SPEED_DECISIONS
from pipelines.evaluate.grounding import Scored, score_2d, score_3d
from pipelines.evaluate.planning import decision_accuracy, regression_mae
from pipelines.evaluate.text import text_scores

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

_TOK = "on gdwm's tokenizer, not the Java PTBTokenizer"
_BLEU = f"BLEU-4 x100, pycocoevalcap Bleu(4) ('closest' reference length) {_TOK}"
_ROUGE = f"ROUGE-L x100, pycocoevalcap Rouge (beta 1.2) {_TOK}"
_CIDER = f"CIDEr x100, pycocoevalcap Cider (n 4, sigma 6, document frequencies of the scored references) {_TOK}"
_MAP2D = "mean over IoU 0.50:0.05:0.95 of COCO 101-point AP, one box per sample ranked by sample order, unparsed = miss"
_ACC = "exact match of the decision (text before the first '.'), malformed = wrong"
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
    "nuinteract/avg": "arithmetic mean of the ten NuInteract metrics",
    "nuinstruct/mae": "MAE of the first number in the text, answers' unit; unparsed predictions left out and counted",
    "nuinstruct/acc": _ACC,
    "nuinstruct/map": _MAP2D,
    "nuinstruct/bleu": _BLEU,
    "nuinstruct/average_star": "(acc + map + bleu - mae) / 4",
    "omnidrive/bleu": _BLEU,
    "omnidrive/cider": _CIDER,
    "omnidrive/rouge_l": _ROUGE,
    "omnidrive/avg": "arithmetic mean of omnidrive bleu, cider, rouge_l",
}
"""What every metric uses (all approximate)."""


@dataclass
class SuiteMapping:
    """Which rows feed each metric group: glob patterns (``fnmatch``, case-sensitive) matched against a row's ``task``
    and its ``category``. Defaults fit our synthetic QA (``pipelines.data.synth.qa``); release data names categories
    ``"<qa_group>/<qa_subtask>"``, e.g. ``nuinteract_rdp=("NuInteract_RD&P/*",)``."""

    nuinteract_rdp: tuple[str, ...] = ("rdp",)
    """Region description & perception: BLEU-4, ROUGE-L, CIDEr over all these rows."""
    nuinteract_vg2d: tuple[str, ...] = ("vg2d",)
    """2D grounding ("<CAM> <box>(x1,y1),(x2,y2)</box>"): mAP, F1, mIoU."""
    nuinteract_vg3d: tuple[str, ...] = ("vg3d",)
    """3D grounding ("center: (x, y, z), size: (l, w, h)"): precision, mAP, F1."""
    nuinteract_plan: tuple[str, ...] = ("plan",)
    """Planning: decision accuracy."""
    nuinstruct_regression: tuple[str, ...] = ("2D_perception_infos",)
    """MAE of the first number (our data: object distances in metres)."""
    nuinstruct_classification: tuple[str, ...] = ("planning_speed", "planning_direction")
    """Decision accuracy."""
    nuinstruct_detection: tuple[str, ...] = ("2D_visual_grounding",)
    """mAP as 2D grounding."""
    nuinstruct_caption: tuple[str, ...] = ("region_description",)
    """BLEU-4."""
    omnidrive_text: tuple[str, ...] = ("region_description", "planning_speed", "planning_direction")
    """BLEU-4, CIDEr, ROUGE-L."""
    decision_labels: tuple[str, ...] | None = SPEED_DECISIONS + DIRECTION_DECISIONS
    """Valid predicted decisions, lowercase (another one is malformed); None accepts any."""


@dataclass
class SuiteResult:
    metrics: dict[str, float] = field(default_factory=dict)
    """By metric name (README: Stages); a metric without samples is absent (never 0)."""
    counts: dict[str, int] = field(default_factory=dict)
    """Samples scored per group (``nuinteract/vg2d``), with ``malformed/<group>`` (unparsed predictions, scored as
    misses) and ``bad_answer/<group>`` (unparsed references, skipped) for the parsed groups."""
    protocol: dict[str, str] = field(default_factory=dict)
    """Metric name -> "approximate: <what it used>; rows: <patterns>"."""

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


def score_predictions(
    rows: Iterable[dict] | Any, mapping: SuiteMapping | None = None, wanted: Collection[str] | None = None
) -> SuiteResult:
    """Every suite's metrics of prediction ``rows`` (dicts or a pyarrow Table), ranked for mAP in the given order;
    with ``wanted``, only the groups those metrics (and the aggregates among them) need."""
    m = mapping or SuiteMapping()
    rows = _rows(rows)
    out = SuiteResult()
    need = None if wanted is None else set(wanted).union(*(AGGREGATES[a] for a in wanted if a in AGGREGATES))

    def run(group: str, score: Callable[[list[str], list[str]], Scored | dict | None], names: dict[str, str]) -> None:
        if need is not None and need.isdisjoint(names.values()):
            return
        patterns = getattr(m, group.replace("/", "_"))
        sel = [r for r in rows if any(fnmatchcase(r[c] or "", p) for p in patterns for c in ("task", "category"))]
        if not sel:
            return
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
                out.protocol[name] = f"approximate: {PROTOCOL[name]}; rows: {', '.join(patterns)}"

    def accuracy(answers: Sequence[str], predictions: Sequence[str]) -> Scored:
        return decision_accuracy(answers, predictions, m.decision_labels)

    run(
        "nuinteract/rdp",
        text_scores,
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
    run("nuinstruct/regression", regression_mae, {"mae": "nuinstruct/mae"})
    run("nuinstruct/classification", accuracy, {"acc": "nuinstruct/acc"})
    run("nuinstruct/detection", score_2d, {"map": "nuinstruct/map"})
    run("nuinstruct/caption", text_scores, {"bleu": "nuinstruct/bleu"})
    run(
        "omnidrive/text",
        text_scores,
        {"bleu": "omnidrive/bleu", "cider": "omnidrive/cider", "rouge_l": "omnidrive/rouge_l"},
    )

    def aggregate(name: str, parts: Sequence[str], value: Callable[..., float]) -> None:
        if all(p in out.metrics for p in parts):
            out.metrics[name] = value(*(out.metrics[p] for p in parts))
            out.protocol[name] = f"approximate: {PROTOCOL[name]}"

    aggregate("nuinteract/avg", AGGREGATES["nuinteract/avg"], lambda *v: sum(v) / len(v))
    aggregate(
        "nuinstruct/average_star",
        AGGREGATES["nuinstruct/average_star"],
        lambda acc, map_, bleu, mae: (acc + map_ + bleu - mae) / 4,
    )
    aggregate("omnidrive/avg", AGGREGATES["omnidrive/avg"], lambda *v: sum(v) / len(v))
    return out


def score_table(table: Any, wanted: Collection[str] | None = None) -> dict[str, float]:
    """The metrics of a ``predictions.parquet`` table (or any subset of its rows, repeats allowed): what
    ``evaluate_qa`` logs, recomputed on bootstrap resamples by ``gdwm compare`` and ``gdwm regress`` (only the
    ``wanted`` ones and what they need)."""
    return score_predictions(table, wanted=wanted).metrics
