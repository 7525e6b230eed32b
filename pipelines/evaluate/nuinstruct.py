"""NuInstruct's protocol on its own answer forms (``SuiteMapping.nuinstruct_protocol: per_subtask``), 0–100 but MAE.

NuInstruct (Ding et al., CVPR 2024, Table 2) scores each subtask with one metric: MAE for its regression subtasks,
accuracy for classification, mAP for the risk subtasks, BLEU for reasoning; each reported metric is the mean of its
subtasks' values, and Average* (VGGDrive, Table 2) is max((Accuracy + mAP + BLEU - MAE) / 4, 0). No evaluation code is
published with it, so the rules below are ours, written from its answer forms, and labelled approximate:

- regression: an answer is a vector ``(x, y)`` where it holds one, else its first number; the error is the absolute
  difference, for a vector the mean of the two components' (``(|dx| + |dy|) / 2``). A prediction without the
  reference's form is malformed: counted and left out of the mean, as ``planning.regression_mae`` does.
- classification: where the reference names objects (``<car>[c1,x1,y1,x2,y2]``) the set of (class, camera) pairs
  must be equal; otherwise the normalised text (lowercase, whitespace collapsed, trailing punctuation dropped).
- risk (mAP): the objects ``<class>[camera,x1,y1,x2,y2]`` of an answer, in order, are its ranked detections; a
  detection matches an unmatched reference object of the same class and camera at IoU >= t, the best one; a sample's
  AP is ``grounding.average_precision`` (COCO 101-point) averaged over IoU 0.50:0.05:0.95. A sample whose reference
  and prediction both name no object (``risk-non``: nothing to report) is not scored (counted as ``empty``); a
  prediction naming none where the reference names some is malformed (AP 0).
- reasoning: BLEU-4 of the subtask's rows as one corpus (``text.text_scores``).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from pipelines.evaluate.grounding import IOU_THRESHOLDS, NUMBER, Scored, average_precision, box_iou
from pipelines.evaluate.planning import parse_number

_VECTOR = re.compile(rf"\(\s*({NUMBER})\s*,\s*({NUMBER})\s*\)")
_COORD = rf"\s*,\s*({NUMBER})"
_OBJECT = re.compile(rf"<\s*([A-Za-z][\w.\- ]*?)\s*>\s*\[\s*(\w+){_COORD * 4}\s*\]")
_OBJECT_START = re.compile(r"<\s*[A-Za-z][\w.\- ]*?\s*>\s*\[")
"""Where an answer begins to name an object: one whose full form does not follow is a malformed object."""


@dataclass(frozen=True)
class RiskObject:
    cls: str
    camera: str
    box: tuple[float, float, float, float]


def parse_value(text: str) -> float | tuple[float, float] | None:
    """The regression value of an answer: its first ``(x, y)`` vector, else its first number; None if neither."""
    v = _VECTOR.search(text or "")
    if v is not None:
        x, y = float(v.group(1)), float(v.group(2))
        return (x, y) if np.isfinite([x, y]).all() else None
    return parse_number(text)


def regression_error(reference: float | tuple[float, float], prediction: str) -> float | None:
    """Absolute error of ``prediction`` against a parsed reference (vector: mean over the components); None when the
    prediction lacks the reference's form."""
    value = parse_value(prediction)
    if isinstance(reference, tuple):
        if not isinstance(value, tuple):
            return None
        return (abs(value[0] - reference[0]) + abs(value[1] - reference[1])) / 2
    return None if value is None or isinstance(value, tuple) else abs(value - reference)


def parse_objects(text: str) -> list[RiskObject] | None:
    """The objects an answer names, in order (class lowercased; the camera as written: ``c1`` or ``CAM_FRONT``);
    None when it begins an object that does not parse (a malformed list)."""
    text = text or ""
    objects = [
        RiskObject(m.group(1).strip().lower(), m.group(2), _ordered([float(v) for v in m.groups()[2:]]))
        for m in _OBJECT.finditer(text)
    ]
    if len(_OBJECT_START.findall(text)) != len(objects) or not all(np.isfinite(o.box).all() for o in objects):
        return None
    return objects


def _ordered(v: list[float]) -> tuple[float, float, float, float]:
    x1, y1, x2, y2 = v
    return min(x1, x2), min(y1, y2), max(x1, x2), max(y1, y2)


def normalised(text: str) -> str:
    """Lowercase, whitespace collapsed, trailing punctuation dropped: the text an accuracy compares."""
    return " ".join((text or "").lower().split()).rstrip(" .,;:!?")


def class_label(text: str) -> str | frozenset[tuple[str, str]] | None:
    """What a classification answer says: the (class, camera) pairs of the objects it names, else its normalised
    text; None for an empty answer or a malformed object list."""
    objects = parse_objects(text)
    if objects is None:
        return None
    if objects:
        return frozenset((o.cls, o.camera) for o in objects)
    return normalised(text) or None


def sample_ap(references: Sequence[RiskObject], detections: Sequence[RiskObject]) -> float:
    """AP (0–100) of one answer's ranked detections against its reference objects, averaged over IoU 0.50:0.95."""
    aps = []
    for t in IOU_THRESHOLDS:
        used = [False] * len(references)
        hits = []
        for d in detections:
            best, at = t, -1
            for i, r in enumerate(references):
                if not used[i] and r.cls == d.cls and r.camera == d.camera and (iou := box_iou(r.box, d.box)) >= best:
                    best, at = iou, i
            if at >= 0:
                used[at] = True
            hits.append(at >= 0)
        aps.append(average_precision(hits, len(references)))
    return float(np.mean(aps))


def regression_scores(answers: Sequence[str], predictions: Sequence[str]) -> Scored:
    """``mae`` over the parsed predictions (answers' unit)."""
    errors, bad, malformed = [], 0, 0
    for answer, prediction in zip(answers, predictions, strict=True):
        reference = parse_value(answer)
        if reference is None:
            bad += 1
            continue
        e = regression_error(reference, prediction)
        if e is None:
            malformed += 1
        else:
            errors.append(e)
    n = len(answers) - bad
    return Scored({"mae": float(np.mean(errors))} if errors else {}, n, malformed, bad)


def classification_scores(answers: Sequence[str], predictions: Sequence[str]) -> Scored:
    """``acc`` (0–100); a prediction that says nothing (or a malformed object list) is wrong and counted."""
    correct, bad, malformed = 0, 0, 0
    for answer, prediction in zip(answers, predictions, strict=True):
        reference = class_label(answer)
        if reference is None:
            bad += 1
            continue
        predicted = class_label(prediction)
        malformed += predicted is None
        correct += predicted == reference
    n = len(answers) - bad
    return Scored({"acc": 100 * correct / n} if n else {}, n, malformed, bad)


@dataclass
class RiskScored(Scored):
    empty: int = 0
    """Samples whose reference and prediction both name no object: nothing to score."""


def risk_scores(answers: Sequence[str], predictions: Sequence[str]) -> RiskScored:
    """``map`` (0–100): the mean over the scored samples of their AP."""
    aps, bad, malformed, empty = [], 0, 0, 0
    for answer, prediction in zip(answers, predictions, strict=True):
        references = parse_objects(answer)
        if references is None:
            bad += 1
            continue
        detections = parse_objects(prediction)
        if detections is None or (references and not detections):
            malformed += 1
            aps.append(0.0)
        elif not references and not detections:
            empty += 1
        else:
            aps.append(sample_ap(references, detections) if references else 0.0)
    return RiskScored({"map": float(np.mean(aps))} if aps else {}, len(aps), malformed, bad, empty)


def per_subtask(
    rows: Sequence[dict], score: Callable[[list[str], list[str]], Scored | dict | None], key: str
) -> tuple[float | None, dict[str, Scored | dict]]:
    """(mean over the subtasks, by the rows' ``category``, of ``score(...)[key]``; each subtask's result). A subtask
    without a value (nothing scored) does not enter the mean."""
    by_subtask: dict[str, list[dict]] = {}
    for r in rows:
        by_subtask.setdefault(r["category"] or "", []).append(r)
    results, values = {}, []
    for name, sel in sorted(by_subtask.items()):
        s = score([r["answer"] or "" for r in sel], [r["prediction"] or "" for r in sel])
        results[name] = s
        metrics = s.metrics if isinstance(s, Scored) else (s or {})
        if key in metrics:
            values.append(metrics[key])
    return (float(np.mean(values)) if values else None), results
