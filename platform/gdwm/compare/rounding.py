"""Numbers as the paper prints them: rounded half up at the printed precision, aggregates as means of printed values.

Python's ``round`` and ``f"{x:.2f}"`` round the binary value half to even, so 41.085 (stored as 41.08499...) prints
41.08; a table typeset by hand, as the paper's are, reads 41.09. Standard library only, so scorers can import it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from decimal import ROUND_HALF_UP, Decimal


def round_half_up(value: float, digits: int) -> float:
    """``value`` rounded half up at ``digits`` decimals, reading it as its shortest repr (41.085 -> 41.09)."""
    if not math.isfinite(value):
        return value
    return float(Decimal(repr(value)).quantize(Decimal(1).scaleb(-digits), rounding=ROUND_HALF_UP))


def fmt(value: float, digits: int, sign: bool = False) -> str:
    """``value`` printed with ``digits`` decimals, rounded half up; ``sign``: a leading + on positive values."""
    if not math.isfinite(value):
        return f"{value:+}" if sign else f"{value}"
    d = Decimal(repr(value)).quantize(Decimal(1).scaleb(-digits), rounding=ROUND_HALF_UP)
    return f"{d:+.{digits}f}" if sign else f"{d:.{digits}f}"


def mean_of_printed(values: Iterable[float], digits: int) -> float:
    """The mean of the values as printed (each rounded half up at ``digits``), summed exactly with ``math.fsum``."""
    printed = [round_half_up(v, digits) for v in values]
    return math.fsum(printed) / len(printed)
