"""Numbers as the paper prints them: rounded half up at the printed precision, and the one average of a table.

Python's ``round`` and ``f"{x:.2f}"`` round the binary value half to even, so 41.085 (stored as 41.08499...) prints
41.08; a table typeset by hand, as the paper's are, reads 41.09. A value is read as its shortest repr (the decimal
it was written or logged as) and rounded in ``Decimal``.

The average of a row (a paper table's Avg. column) is the mean of the values *as
printed*, computed exactly in ``Decimal``: the suites that log it, ``gdwm compare`` (which recomputes it for every row
from its printed cells, reported rows included), ``gdwm regress`` and every report use :func:`mean_of_printed`. A
binary mean can land just under a tie (73.49 and 54.16: ``math.fsum`` then ``/ 2`` gives 63.824999999999996, which
prints 63.82; the printed mean is 63.825 -> 63.83). Standard library only, so scorers can import it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from decimal import ROUND_HALF_UP, Context, Decimal


def printed(value: float, digits: int) -> Decimal:
    """``value`` as printed with ``digits`` decimals: its shortest repr, rounded half up (41.085 -> 41.09)."""
    return Decimal(repr(value)).quantize(Decimal(1).scaleb(-digits), rounding=ROUND_HALF_UP)


def round_half_up(value: float, digits: int) -> float:
    """``value`` rounded half up at ``digits`` decimals, reading it as its shortest repr (41.085 -> 41.09)."""
    if not math.isfinite(value):
        return value
    return float(printed(value, digits))


def fmt(value: float, digits: int, sign: bool = False) -> str:
    """``value`` printed with ``digits`` decimals, rounded half up; ``sign``: a leading + on positive values."""
    if not math.isfinite(value):
        return f"{value:+}" if sign else f"{value}"
    d = printed(value, digits)
    return f"{d:+.{digits}f}" if sign else f"{d:.{digits}f}"


def fmt_significant(value: float, digits: int = 4) -> str:
    """``value`` to ``digits`` significant digits, half up: 24.775 -> ``24.78``, 0.00123456 -> ``0.001235``."""
    if not math.isfinite(value):
        return f"{value}"
    d = Context(prec=digits, rounding=ROUND_HALF_UP).create_decimal(repr(value))
    text = f"{d:f}"
    return text.rstrip("0").rstrip(".") if "." in text else text


def mean_of_printed(values: Iterable[float], digits: int) -> float:
    """The mean of the values as printed (each rounded half up at ``digits``), exact in ``Decimal``; returned as the
    float nearest to it, whose repr is that decimal, so printing it (``fmt``) rounds the true mean: 24.775 -> 24.78.
    """
    values = list(values)
    if not values:
        raise ValueError("mean_of_printed: no values")
    if not all(math.isfinite(v) for v in values):
        return math.fsum(values) / len(values)  # nan or inf: nothing to print exactly
    return float(sum((printed(v, digits) for v in values), Decimal(0)) / len(values))
