"""Deterministic train/val assignment of whole scenes (no scene is in both splits)."""

from __future__ import annotations

from collections.abc import Sequence


def split_scenes(scene_ids: Sequence, val_fraction: float) -> dict:
    """The last ``round(n * val_fraction)`` scenes in the given order are ``val`` (at least one when the
    fraction is positive and there are two or more scenes, never all of them); the rest ``train``."""
    n = len(scene_ids)
    n_val = min(n - 1, max(1, round(n * val_fraction))) if val_fraction > 0 and n > 1 else 0
    return {s: ("val" if i >= n - n_val else "train") for i, s in enumerate(scene_ids)}
