"""Decision accuracy (planning / classification) and regression MAE (DESIGN §11; approximate).

A decision is the answer's text before its first "." ("Turn left. Reason: ..." -> "turn left"), lowercased with
whitespace collapsed; a prediction without one, or outside the label set when one is given, is malformed: counted
and wrong. A regression value is the first number in the text; a prediction without one is malformed: counted and
left out of the mean (MAE is over the parsed predictions; it is absent when none parsed).
"""

from __future__ import annotations

import re
from collections.abc import Sequence

import numpy as np

from pipelines.evaluate.grounding import Scored

_NUMBER = re.compile(r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?")


def parse_decision(text: str, labels: Sequence[str] | None = None) -> str | None:
    """The decision label at the head of ``text``, or None (empty, or not in ``labels`` when given)."""
    decision = " ".join((text or "").split(".", 1)[0].lower().split()).strip(" ,;:!?")
    if not decision or (labels is not None and decision not in labels):
        return None
    return decision


def parse_number(text: str) -> float | None:
    """The first number in ``text`` (None if there is none or it is not finite)."""
    m = _NUMBER.search(text or "")
    return float(m.group()) if m is not None and np.isfinite(float(m.group())) else None


def decision_accuracy(
    answers: Sequence[str], predictions: Sequence[str], labels: Sequence[str] | None = None
) -> Scored:
    """``acc`` (0–100): share of samples whose predicted decision equals the reference's."""
    correct, n, malformed, bad = 0, 0, 0, 0
    for answer, prediction in zip(answers, predictions, strict=True):
        gt = parse_decision(answer)
        if gt is None:
            bad += 1
            continue
        n += 1
        pred = parse_decision(prediction, labels)
        malformed += pred is None
        correct += pred == gt
    return Scored({"acc": 100 * correct / n} if n else {}, n, malformed, bad)


def regression_mae(answers: Sequence[str], predictions: Sequence[str]) -> Scored:
    """``mae``: mean absolute error of the first numbers, in the answers' unit (metres for distances), not x100."""
    errors, n, bad = [], 0, 0
    for answer, prediction in zip(answers, predictions, strict=True):
        gt = parse_number(answer)
        if gt is None:
            bad += 1
            continue
        n += 1
        if (pred := parse_number(prediction)) is not None:
            errors.append(abs(pred - gt))
    return Scored({"mae": float(np.mean(errors))} if errors else {}, n, n - len(errors), bad)
