"""How ``make test`` spreads the whole suite over the machine's cores (pytest-xdist, ``-n 2 --dist loadfile``).

A worker takes whole files: a module's fixtures (a toy launch several tests read, a sweep) are built once, on one
worker. Files that share an expensive session fixture (``TOGETHER``) go to one worker together, so it is built
once, not once per worker. Files marked ``heavy`` (minutes of launches or a whole pipeline) start first, longest
first, so the suite does not end with one worker finishing a long file while the other has nothing left.
"""

from __future__ import annotations

import pytest

TOGETHER = {
    "tiny_run": ("tests/pipelines/test_determinism.py", "tests/pipelines/test_stages_e2e.py"),
    "demo_sweep": ("tests/pipelines/test_demo_table.py", "tests/pipelines/test_nightly.py"),
}
"""Session fixture -> the files that use it (tests/pipelines/conftest.py: the tiny real-pipeline run, the demo's
sweep); collection fails naming a file that uses one and is not listed here."""

_UNIT = {path: f"<{name}>" for name, paths in TOGETHER.items() for path in paths}
"""File -> its scheduling unit when it is not its own."""


def _unit(nodeid: str) -> str:
    path = nodeid.split("::", 1)[0]
    return _UNIT.get(path, path)


@pytest.hookimpl(optionalhook=True)  # xdist's hook: unknown with -p no:xdist (make test TEST_WORKERS=1)
def pytest_xdist_make_scheduler(config: pytest.Config, log):
    """``--dist loadfile`` with the files of ``TOGETHER`` as one unit each. (xdist's own ``loadgroup`` would do it
    with marks, but under pytest 9 its group suffix no longer reaches the node ids it schedules by.)"""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class FilesTogether(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return _unit(nodeid)

    return FilesTogether(config, log)


def _minutes(item: pytest.Item) -> float:
    mark = item.get_closest_marker("heavy")
    if mark is None:
        return 0.0
    return float(mark.args[0] if mark.args else mark.kwargs.get("minutes", 1))


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Units with heavy files first, longest first (xdist hands them out in this order with
    ``--no-loadscope-reorder``); the order inside a file is kept (its tests may build on one another's runs). Every
    worker sorts alike, so xdist sees one collection."""
    for item in items:
        path = item.nodeid.split("::", 1)[0]
        for name, paths in TOGETHER.items():
            if name in getattr(item, "fixturenames", ()) and path not in paths:
                raise pytest.UsageError(
                    f"{path} uses the session fixture '{name}': list it in TOGETHER (tests/conftest.py) so one "
                    "worker builds it once"
                )
    units: dict[str, list[pytest.Item]] = {}
    minutes: dict[str, float] = {}
    for item in items:
        path = item.nodeid.split("::", 1)[0]
        units.setdefault(_unit(path), []).append(item)
        minutes[path] = max(minutes.get(path, 0.0), _minutes(item))
    weight = {u: sum(minutes[f] for f in {i.nodeid.split("::", 1)[0] for i in its}) for u, its in units.items()}
    order = sorted(units, key=lambda u: -weight[u])  # stable: the rest stays in collection order
    items[:] = [i for u in order for i in units[u]]
