"""Building a dataset for a command: light (no Ray, no MLflow), so ``gdwm data synth`` starts fast."""

from __future__ import annotations

import time
from pathlib import Path

from hydra.utils import get_method
from omegaconf import DictConfig

from gdwm.term import console, print_dataset_summary


def build_dataset(cfg: DictConfig, source: str | None) -> None:
    """Build the dataset selected by ``data=`` (published atomically by its builder), then print its summary."""
    root = Path(cfg.data.root)
    t0 = time.perf_counter()
    get_method(cfg.data.builder)(cfg.data, root=root, source=source, overwrite=cfg.overwrite)
    console.print(f"built {cfg.data.name} in {time.perf_counter() - t0:.1f} s")
    print_dataset_summary(get_method(cfg.data.summarizer)(root))
