"""Base config of every dataset in the ``data/`` group (conf/data/*.yaml)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class DatasetConfig:
    """Fields every ``data/`` option has; each producer subclasses it next to its code."""

    name: str = "???"
    """Dataset name; also the folder under ``<workdir>/data/``."""
    root: str = "${workdir}/data/${.name}"
    """Where the published dataset lives (a local directory)."""
    builder: str = "???"
    """Dotted path of ``build(cfg, root, source, overwrite) -> Path`` that produces this dataset."""
    needs_source: bool = True
    """Whether ``build`` reads an input directory (``source=``); one that does not is generated on demand."""
    planner: str | None = None
    """Dotted path of ``plan(cfg) -> list[str]``: checks the ``data.*`` keys and returns the scene ids ``build``
    would write, writing nothing (a dry run's plan; a bad key is exit 2 before anything is generated)."""
    summarizer: str = "pipelines.data.summary.summarize"
    """Dotted path of ``summarize(root) -> dict`` used by ``gdwm data info``."""
