"""Decision accuracy (planning / classification) and regression MAE (approximate).

A decision is the answer's text before its first "." ("Turn left. Reason: ..." -> "turn left"), lowercased with
whitespace collapsed (``head``), or the label the text names first, as whole words (``first``: "The ego car should
go straight." -> "go straight"); a prediction without one, or outside the label set when one is given, is malformed:
counted and wrong. A regression value is the first number in the text; a prediction without one is malformed: counted
and left out of the mean (MAE is over the parsed predictions; it is absent when none parsed).
"""

from __future__ import annotations

import re
from collections.abc import Sequence

import numpy as np

from pipelines.evaluate.grounding import NUMBER, Scored, parsed_pairs

_NUMBER = re.compile(NUMBER)


def parse_decision(text: str, labels: Sequence[str] | None = None, match: str = "head") -> str | None:
    """The decision label of ``text`` (``match``: ``head`` or ``first``, see the module docstring), or None (empty, or
    not in ``labels`` when given; ``first`` needs ``labels``)."""
    if match == "first":
        if not labels:
            raise ValueError("parse_decision: match='first' needs the labels to look for")
        return _first_label(text, labels)
    decision = " ".join((text or "").split(".", 1)[0].lower().split()).strip(" ,;:!?")
    if not decision or (labels is not None and decision not in labels):
        return None
    return decision


def _first_label(text: str, labels: Sequence[str]) -> str | None:
    """The label whose first whole-word occurrence in ``text`` starts earliest (the longer one at the same place)."""
    words = " ".join((text or "").lower().split())
    found = []
    for label in labels:
        m = re.search(rf"(?<![\w-]){re.escape(' '.join(label.lower().split()))}(?![\w-])", words)
        if m is not None:
            found.append((m.start(), -len(label), label))
    return min(found)[2] if found else None


def parse_number(text: str) -> float | None:
    """The first number in ``text`` (None if there is none or it is not finite)."""
    m = _NUMBER.search(text or "")
    return float(m.group()) if m is not None and np.isfinite(float(m.group())) else None


def decision_accuracy(
    answers: Sequence[str], predictions: Sequence[str], labels: Sequence[str] | None = None, match: str = "head"
) -> Scored:
    """``acc`` (0–100): share of samples whose predicted decision equals the reference's (both read by ``match``)."""
    ref_labels = labels if match == "first" else None  # head: any reference decision is a label

    def ref(text: str) -> str | None:
        return parse_decision(text, ref_labels, match)

    def pred(text: str) -> str | None:
        return parse_decision(text, labels, match)

    pairs, bad = parsed_pairs(answers, predictions, ref, pred)
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
