"""How ``make test`` spreads the whole suite over the machine's cores (pytest-xdist, ``-n 2 --dist loadgroup``).

A worker takes whole files: a module's fixtures (a toy launch several tests read, a sweep) are built once, on
one worker. Files marked with one ``xdist_group`` go to the same worker together: a session fixture they share
(the tiny real-pipeline run) is built once, not once per worker. Files marked ``heavy`` (minutes of one launch or
a whole pipeline) start first, longest first, so the suite does not end on one worker finishing a long file
while the other has nothing left.
"""

from __future__ import annotations

import pytest


def pytest_xdist_make_scheduler(config: pytest.Config, log):
    """``--dist loadgroup`` with whole files as the unit where a file has no ``xdist_group`` (xdist's own splits
    such a file test by test, building its module fixtures on every worker that gets one of its tests)."""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadGroupScheduling

    class FilesAndGroups(LoadGroupScheduling):
        def _split_scope(self, nodeid: str) -> str:
            if nodeid.rfind("@") > nodeid.rfind("]"):  # xdist appends "@<group>" to a grouped test's id
                return nodeid.rsplit("@", 1)[-1]
            return nodeid.split("::", 1)[0]

    return FilesAndGroups(config, log)


def _minutes(item: pytest.Item) -> float:
    mark = item.get_closest_marker("heavy")
    if mark is None:
        return 0.0
    return float(mark.args[0] if mark.args else mark.kwargs.get("minutes", 1))


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Files (and groups) with heavy tests first, longest first; the order inside a file is kept (its tests may
    build on one another's runs). Every worker sorts alike, so xdist sees one collection."""
    units: dict[str, list[pytest.Item]] = {}
    minutes: dict[str, float] = {}
    for item in items:
        group = item.get_closest_marker("xdist_group")
        path = item.nodeid.split("::")[0]
        unit = f"@{group.args[0] if group.args else group.kwargs['name']}" if group else path
        units.setdefault(unit, []).append(item)
        minutes[path] = max(minutes.get(path, 0.0), _minutes(item))
    weight = {u: sum(minutes[f] for f in {i.nodeid.split("::")[0] for i in its}) for u, its in units.items()}
    order = sorted(units, key=lambda u: -weight[u])  # stable: the rest stays in collection order
    items[:] = [i for u in order for i in units[u]]
