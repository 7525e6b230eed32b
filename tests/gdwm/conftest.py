"""Shared fixtures of the gdwm tests."""

import pytest
import ray


@pytest.fixture(scope="session")
def ray_local():
    """One local Ray (2 CPUs, token auth as shipped) for the whole session."""
    ctx = ray.init(num_cpus=2, include_dashboard=False)
    yield ctx
    ray.shutdown()
