"""Shared fixtures of the gdwm tests."""

import pytest
import ray


@pytest.fixture(scope="session")
def ray_local():
    """One local Ray (2 CPUs, token auth as shipped) for the whole session: a new one, never a cluster another
    xdist worker started meanwhile (a sim cluster's head is the machine's "current cluster" while it runs)."""
    ctx = ray.init(address="local", num_cpus=2, include_dashboard=False)
    yield ctx
    ray.shutdown()


@pytest.fixture(scope="session")
def team(tmp_path_factory):
    """A team's store, started once per session: MLflow with basic-auth on PostgreSQL (run as the unprivileged user
    ``postgres`` when the tests run as root), artifacts on S3 (moto), all on loopback (``tests/gdwm/servers.py``)."""
    from tests.gdwm.servers import pg_bindir, team_store

    if pg_bindir() is None:
        pytest.skip("PostgreSQL is not installed (make setup installs Debian's postgresql)")
    with team_store(tmp_path_factory.mktemp("team-store")) as store:
        yield store
