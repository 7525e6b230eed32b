"""2D and 3D visual grounding metrics, 0–100 (no official public code, so approximate).

Every sample has one ground-truth object and at most one predicted one (the first box or centre in the answer).
A prediction that does not parse is no prediction: a miss that lowers recall, never a false positive. So, at one
threshold, with N samples, P parsed predictions and TP of them matching:
precision = TP / P (0 when P = 0), recall = TP / N, F1 = 2 precision recall / (precision + recall).
AP is COCO's 101-point interpolated AP with predictions ranked by sample order (answers carry no scores) and N
ground truths; written here because pycocotools' COCOeval needs images, categories and scores we do not have.
"""

from __future__ import annotations

import functools
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

IOU_THRESHOLDS = np.linspace(0.5, 0.95, 10)
"""2D match thresholds (COCO): a box matches when IoU >= t."""
MATCH_IOU = 0.5
"""2D threshold of precision and F1."""
DIST_THRESHOLDS_M = (0.5, 1.0, 2.0, 4.0)
"""3D match thresholds (nuScenes detection): a centre matches when its ego-xy distance < t."""
MATCH_DIST_M = 2.0
"""3D threshold of precision and F1."""
RECALL_POINTS = np.linspace(0.0, 1.0, 101)

NUMBER = r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?"
"""A decimal number in an answer (the grounding and the regression parsers share it)."""
_NUM = NUMBER
_PAIR = rf"\(\s*({_NUM})\s*,\s*({_NUM})\s*\)"
_BOX = re.compile(rf"(?:<(\w+)>\s*)?<box>\s*{_PAIR}\s*,\s*{_PAIR}\s*</box>")
_QUAD = rf"\[\s*({_NUM})\s*,\s*({_NUM})\s*,\s*({_NUM})\s*,\s*({_NUM})\s*\]"
_BOX_LIST = re.compile(rf"(?:<(\w+)>\s*)?<box>\s*\[?\s*{_QUAD}")
"""InternVL's grounding form (NuInteract's conversations): ``<box>[[x1, y1, x2, y2]]</box>``, the first box of the
list; its 0-1000 normalised coordinates are compared as they are, like the references'."""
_TRIPLE = rf"\(\s*({_NUM})\s*,\s*({_NUM})\s*,\s*({_NUM})\s*\)"
_CENTRE = re.compile(rf"cent(?:er|re)\s*:?\s*{_TRIPLE}", re.IGNORECASE)
_SIZE = re.compile(rf"size\s*:?\s*{_TRIPLE}", re.IGNORECASE)


@dataclass
class Scored:
    """Metrics of one group of samples and how many samples were usable."""

    metrics: dict[str, float]
    """By name; empty when nothing could be scored."""
    samples: int
    """Samples scored (those whose reference answer parsed)."""
    malformed: int = 0
    """Scored samples whose prediction did not parse (each a miss)."""
    bad_answers: int = 0
    """Samples skipped because their reference answer did not parse."""


# The parsers are pure and a bootstrap re-scores the same answers for every resample (1,000 times a table cell):
# memoised, each distinct text is parsed once. Their results are tuples, never mutated.
@functools.lru_cache(maxsize=1 << 16)
def parse_box(text: str) -> tuple[str | None, tuple[float, float, float, float]] | None:
    """(camera tag or None, (x1, y1, x2, y2) with x1 <= x2, y1 <= y2) of the first ``<box>(x1,y1),(x2,y2)</box>`` or
    ``<box>[[x1, y1, x2, y2]]</box>``."""
    found = [m for m in (_BOX.search(text or ""), _BOX_LIST.search(text or "")) if m is not None]
    if not found:
        return None
    m = min(found, key=lambda f: f.start())
    x1, y1, x2, y2 = v = [float(t) for t in m.groups()[1:]]
    if not np.isfinite(v).all():
        return None
    return m.group(1), (min(x1, x2), min(y1, y2), max(x1, x2), max(y1, y2))


@functools.lru_cache(maxsize=1 << 16)
def parse_centre_size(text: str) -> tuple[tuple[float, float, float], tuple[float, float, float] | None] | None:
    """(centre, size or None) of "center: (x, y, z), size: (l, w, h)"; None without a centre (size is not scored)."""
    c = _CENTRE.search(text or "")
    if c is None or not np.isfinite(centre := tuple(float(v) for v in c.groups())).all():
        return None
    s = _SIZE.search(text)
    return centre, (None if s is None else tuple(float(v) for v in s.groups()))


def box_iou(a: Sequence[float], b: Sequence[float]) -> float:
    """Intersection over union (0–1) of two (x1, y1, x2, y2) boxes; 0 when the union is empty."""
    iw = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    ih = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = iw * ih
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def average_precision(hits: Sequence[bool], num_gt: int) -> float:
    """COCO 101-point interpolated AP (0–100): ``hits[k]`` says whether the k-th ranked prediction matches, ``num_gt``
    counts all samples (unanswered ones too)."""
    hit = np.asarray(hits, dtype=bool)
    if num_gt <= 0 or hit.size == 0:
        return 0.0
    tp = np.cumsum(hit)
    recall = tp / num_gt
    precision = np.maximum.accumulate((tp / np.arange(1, hit.size + 1))[::-1])[::-1]  # COCOeval's envelope
    idx = np.searchsorted(recall, RECALL_POINTS, side="left")
    q = np.where(idx < hit.size, precision[np.minimum(idx, hit.size - 1)], 0.0)
    return 100 * float(q.mean())


def precision_recall_f1(hits: Sequence[bool], num_gt: int) -> tuple[float, float, float]:
    """(precision, recall, F1), 0–100, of parsed predictions ``hits`` over ``num_gt`` samples."""
    tp = float(np.sum(hits))
    p = tp / len(hits) if len(hits) else 0.0
    r = tp / num_gt if num_gt else 0.0
    return 100 * p, 100 * r, (200 * p * r / (p + r) if p + r else 0.0)


def parsed_pairs(
    answers: Sequence[str], predictions: Sequence[str], parse_ref: Callable, parse_pred: Callable
) -> tuple[list[tuple[Any, Any]], int]:
    """(parsed reference, parsed prediction or None) of every sample whose reference parses; and how many did not
    (those are counted as bad answers, not scored)."""
    pairs, bad = [], 0
    for answer, prediction in zip(answers, predictions, strict=True):
        gt = parse_ref(answer)
        if gt is None:
            bad += 1
            continue
        pairs.append((gt, parse_pred(prediction)))
    return pairs, bad


def score_2d(answers: Sequence[str], predictions: Sequence[str]) -> Scored:
    """``map`` (IoU 0.50:0.05:0.95), ``f1`` (IoU 0.5) and ``miou`` (misses count 0), in sample order.

    A box tagged with another camera than the reference's has IoU 0.
    """
    pairs, bad = parsed_pairs(answers, predictions, parse_box, parse_box)
    n = len(pairs)
    if n == 0:
        return Scored({}, 0, 0, bad)
    ok = np.asarray([box is not None for _, box in pairs])
    iou = np.asarray([
        box_iou(gt[1], box[1]) if box is not None and (gt[0] is None or box[0] is None or gt[0] == box[0]) else 0.0
        for gt, box in pairs
    ])  # fmt: skip
    metrics = {
        "map": float(np.mean([average_precision(iou[ok] >= t, n) for t in IOU_THRESHOLDS])),
        "f1": precision_recall_f1(iou[ok] >= MATCH_IOU, n)[2],
        "miou": 100 * float(iou.mean()),
    }
    return Scored(metrics, n, int((~ok).sum()), bad)


def score_3d(answers: Sequence[str], predictions: Sequence[str]) -> Scored:
    """``map`` (mean AP over 0.5/1/2/4 m), ``precision`` and ``f1`` (2 m) by ego-xy centre distance, in sample order."""
    pairs, bad = parsed_pairs(answers, predictions, parse_centre_size, parse_centre_size)
    n = len(pairs)
    if n == 0:
        return Scored({}, 0, 0, bad)
    # distances of the parsed predictions only
    d = np.asarray([float(np.hypot(p[0][0] - g[0][0], p[0][1] - g[0][1])) for g, p in pairs if p is not None])
    p, _, f1 = precision_recall_f1(d < MATCH_DIST_M, n)
    ap = [average_precision(d < t, n) for t in DIST_THRESHOLDS_M]
    return Scored({"map": float(np.mean(ap)), "precision": p, "f1": f1}, n, n - d.size, bad)
