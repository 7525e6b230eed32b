"""Training helpers of the platform."""

from __future__ import annotations

from itertools import pairwise

import pytest

from gdwm.training import warmup_cosine_lr


def test_warmup_cosine_lr_ramps_then_decays_to_the_floor():
    lr = [warmup_cosine_lr(s, 1e-3, warmup_steps=10, total_steps=110) for s in range(111)]
    assert lr[0] == pytest.approx(1e-4) and lr[9] == pytest.approx(1e-3)  # linear warm-up to the base rate
    assert lr[60] == pytest.approx(1e-3 * (0.1 + 0.9 * 0.5))  # half-way through the cosine
    assert lr[110] == pytest.approx(1e-4)  # floor 10 %
    assert all(a >= b for a, b in pairwise(lr[10:]))
    assert warmup_cosine_lr(5, 2.0, warmup_steps=0, total_steps=5) == pytest.approx(0.2)
