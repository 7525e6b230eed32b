"""model_zoo.lru.LRU: computed once, dropped least recently used first, by entries and by bytes."""

from __future__ import annotations

import pytest

from model_zoo.lru import LRU


def test_values_are_computed_once_and_the_least_recently_used_go_first():
    calls = []
    lru: LRU[str] = LRU(items=2)
    get = lambda k: lru.get(k, lambda: calls.append(k) or k.upper())  # noqa: E731
    assert [get("a"), get("b"), get("a")] == ["A", "B", "A"] and calls == ["a", "b"]
    get("c")  # over 2 entries: "b" (used least recently) goes, "a" stays
    assert ("a" in lru, "b" in lru, "c" in lru, len(lru)) == (True, False, True, 2)
    get("b")
    assert calls == ["a", "b", "c", "b"]


def test_a_byte_bound_drops_until_it_holds_and_keeps_the_last_value_whatever_its_size():
    lru: LRU[bytes] = LRU(nbytes=10, size=len)
    for k, n in (("a", 4), ("b", 4), ("c", 4)):
        lru.get(k, lambda n=n: b"x" * n)
    assert ("a" in lru, lru.total) == (False, 8)
    lru.get("big", lambda: b"x" * 25)
    assert (len(lru), lru.total) == (1, 25)
    with pytest.raises(ValueError, match="LRU: a bound in bytes needs size="):
        LRU(nbytes=10)
