"""Decision accuracy (planning / classification) and regression MAE (approximate).

A decision is the answer's text before its first "." ("Turn left. Reason: ..." -> "turn left"), lowercased with
whitespace collapsed; a prediction without one, or outside the label set when one is given, is malformed: counted
and wrong. A regression value is the first number in the text; a prediction without one is malformed: counted and
left out of the mean (MAE is over the parsed predictions; it is absent when none parsed).
"""

from __future__ import annotations

import re
from collections.abc import Sequence

import numpy as np

from pipelines.evaluate.grounding import NUMBER, Scored, parsed_pairs

_NUMBER = re.compile(NUMBER)


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
    pairs, bad = parsed_pairs(answers, predictions, parse_decision, lambda text: parse_decision(text, labels))
    n = len(pairs)
    correct = sum(pred == gt for gt, pred in pairs)
    malformed = sum(pred is None for _, pred in pairs)
    return Scored({"acc": 100 * correct / n} if n else {}, n, malformed, bad)


def regression_mae(answers: Sequence[str], predictions: Sequence[str]) -> Scored:
    """``mae``: mean absolute error of the first numbers, in the answers' unit (metres for distances), not x100."""
    pairs, bad = parsed_pairs(answers, predictions, parse_number, parse_number)
    errors = [abs(pred - gt) for gt, pred in pairs if pred is not None]
    n = len(pairs)
    return Scored({"mae": float(np.mean(errors))} if errors else {}, n, n - len(errors), bad)
