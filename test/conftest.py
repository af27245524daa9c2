"""Shared test settings: hypothesis profiles sized for a 2-core CI machine; fixtures more than
one folder's tests build (once per run)."""

import os
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

settings.register_profile("ci", deadline=None, max_examples=25, derandomize=True,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("dev", deadline=None, max_examples=25, suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("thorough", deadline=None, max_examples=500, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci" if os.environ.get("CI") else "dev"))


# The drift drive that test_correction.py (core) and test_node_corrections.py (ROS) both map:
# 40 scans of 16 beams, odometry 8 degrees per 100 m and 1 % off, the SLAM closing the loop
# before scan DRIFT_CLOSURE, moving traffic. Built once per test run, read only by its users.
DRIFT_FRAMES, DRIFT_CLOSURE = 40, 25


@pytest.fixture(scope="session")
def drift_drive(tmp_path_factory) -> Path:
    """The dataset root (sequence 00) of the shared drift drive."""
    from convbki_core.tools import synth

    root = tmp_path_factory.mktemp("drift_drive")
    assert synth.main(["--out", str(root), "--sequence", "00", "--frames", str(DRIFT_FRAMES), "--seed", "24",
                       "--speed", "15", "--beams", "16", "--azimuth-steps", "500", "--drift", "8", "--drift-scale",
                       "0.01", "--loop-closure", str(DRIFT_CLOSURE), "--movers", "6", "--quiet"]) == 0
    return root


@pytest.fixture(scope="session")
def real_noisy(tmp_path_factory):
    """``real_noisy(*sequences)``: the root of a dataset holding those real SemanticKITTI
    sequences with ``label_noise``'s input segmentation (its defaults: seed 0, mIoU 0.55), each
    written once per run whichever test asks first (test/core/test_real_scans.py; the same input
    as test/ros/test_real_scans_node.py's). Skips the test where the real scans are absent."""
    root = tmp_path_factory.mktemp("real_noisy")
    written: set[str] = set()

    def noisy(*sequences: str) -> Path:
        from helpers import real_sequence

        from convbki_core.tools import label_noise

        for sequence in sequences:
            source = real_sequence(sequence)
            if sequence not in written:
                assert label_noise.main(["--dataset", str(source), "--sequence", sequence, "--out", str(root),
                                         "--quiet"]) == 0
                written.add(sequence)
        return root

    return noisy


# -- early starts ---------------------------------------------------------------------------------
@pytest.fixture(scope="session", autouse=True)
def early_starts(request, tmp_path_factory):
    """A test marked ``early_start(work)`` has ``work(tmp_path_factory)``, a slow part that mostly
    waits (a replay with a stop longer than DDS's lease), started in a thread when the run
    begins, beside the tests before it; the test takes what it returned from ``early_result``."""
    from concurrent.futures import ThreadPoolExecutor

    started = {}
    tmp_path_factory.getbasetemp()  # made here: two threads making it at once would make two
    items = [item for item in request.session.items if item.get_closest_marker("early_start")]
    pool = ThreadPoolExecutor(max_workers=max(1, len(items)))
    for item in items:
        started[item.nodeid] = pool.submit(item.get_closest_marker("early_start").args[0], tmp_path_factory)
    yield started
    pool.shutdown(wait=True, cancel_futures=True)


@pytest.fixture
def early_result(request, early_starts):
    """What the test's ``early_start`` work returned (its failure raised here)."""
    return early_starts[request.node.nodeid].result()
