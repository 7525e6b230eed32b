"""Base config of every dataset in the ``data/`` group (conf/data/*.yaml)."""

from __future__ import annotations

from dataclasses import dataclass, field

from annotated_types import Interval

SEED = Interval(ge=0, le=2**32 - 1)
"""A seed's range (numpy's legacy one, as ``gdwm.api.SEED``; the data layer imports nothing of gdwm)."""


@dataclass
class DatasetConfig:
    """Fields every ``data/`` option has; each producer subclasses it next to its code."""

    name: str = "???"
    """Dataset name; also the folder under ``<workdir>/data/``."""
    root: str = "${workdir}/data/${.name}"
    """Where the published dataset lives (a local directory)."""
    builder: str = "???"
    """Dotted path of ``build(cfg, root, source, overwrite) -> Path`` that produces this dataset."""
    build_command: str | None = None
    """The command that builds it (``gdwm data <sub>``, registered in ``pipelines.commands``): what gdwm's messages
    about a missing or mismatched dataset tell the user to run."""
    needs_source: bool = True
    """Whether ``build`` reads an input directory (``source=``); one that does not is generated on demand."""
    planner: str | None = None
    """Dotted path of ``plan(cfg) -> list[str]``: checks the ``data.*`` keys and returns the scene ids ``build``
    would write, writing nothing (a dry run's plan; a bad key is exit 2 before anything is generated)."""
    checker: str | None = "pipelines.data.check.check_files"
    """Dotted path of ``check(root, files)``: reads the files that differ from what ``dataset.json`` recorded and
    raises one error naming a bad one (an unreadable image, a non-finite reference box) before any stage runs."""
    summarizer: str = "pipelines.data.summary.render"
    """Dotted path of ``render(root) -> list`` of lines and rich tables: the dataset's summary, which gdwm prints
    (``gdwm data info``, and after a build)."""
    tables: list[str] = field(default_factory=list)
    """What a dataset of this option holds (tables, per-scene file kinds such as ``images``; see
    ``layout.held_tables``) before it exists: a dry run of a dataset generated on demand checks the stages' needs
    against it. Once built, its ``dataset.json`` ``tables`` is what counts. Empty: unknown, nothing is checked."""
