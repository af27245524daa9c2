"""Shared test settings: hypothesis profiles sized for a 2-core CI machine, and the check that
install/ holds the tree's files (for the tests that run the installed package)."""

import os

import pytest
from hypothesis import HealthCheck, settings

settings.register_profile("ci", deadline=None, max_examples=25, derandomize=True,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("dev", deadline=None, max_examples=25, suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("thorough", deadline=None, max_examples=500, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci" if os.environ.get("CI") else "dev"))


@pytest.fixture(scope="module")
def current_install():
    """For the tests that run the installed package (install/): one line, and a failure, when it
    is older than the tree (run `make setup`), rather than an old node compared with new code."""
    from ros_helpers import require_current_install

    require_current_install()
