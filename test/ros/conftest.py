"""Fixtures of the ROS-side tests."""

import pytest
from ros_helpers import require_current_install


@pytest.fixture(scope="module")
def current_install():
    """For the tests that run the installed package (install/): one line, and a failure, when it
    is older than the tree (run `make setup`), rather than an old node compared with new code."""
    require_current_install()
