"""First contact: a node started on a fresh install (no compiled-kernel cache) keeps up with a
10 Hz bag replayed the moment it says ready, and under numba's ``workqueue`` threading layer
(not thread-safe) the node's update and publishing threads map a whole replay without ever
entering parallel kernels together. Real processes over DDS, a real bag, the shipped params.

The node's own counters on /diagnostics tell whether it kept up: reports counted, not seconds."""

import re
import signal

import pytest
from mapper_rig import Stats
from ros_helpers import REPO, NodeLog, Probe, domain_id, start

from convbki_core.tools.synth import main as synth
from convbki_ros.tools.kitti_to_bag import main as kitti_to_bag

FRAMES = 40  # 4 s at 10 Hz
DIAGNOSTICS_PERIOD = 0.5
# "Current within a couple of seconds of the bag's end": this many diagnostics reports after it.
REPORTS_AFTER_THE_END = 5
COLD_START_LIMIT = 600  # seconds a cold node may take to compile before it says ready, on a loaded machine


def _drive_and_bag(root):
    assert synth(["--out", str(root / "data"), "--sequence", "00", "--frames", str(FRAMES), "--seed", "4",
                  "--beams", "32", "--azimuth-steps", "900", "--movers", "6", "--noise-strength", "0.35",
                  "--quiet"]) == 0
    assert kitti_to_bag(["--dataset", str(root / "data"), "--sequence", "00", "--out", str(root / "bag")]) == 0
    return root / "bag"


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    """A 40-scan drive with movers (32 beams, about 25,000 points a scan) and its bag, made in a
    thread while the first test's node starts (``bag.result()`` waits for it)."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=1) as pool:
        yield pool.submit(_drive_and_bag, tmp_path_factory.mktemp("first_contact"))


class Replay:
    """The mapper with the shipped params, a probe on /diagnostics (and on the map topics when
    asked), and play_bag started the moment the node says ready."""

    def __init__(self, tmp_path, bag, env: dict, listen_to_outputs: bool = False):
        from diagnostic_msgs.msg import DiagnosticArray
        from sensor_msgs.msg import PointCloud2

        domain = domain_id()
        self.probe = Probe(domain)
        self.diagnostics = self.probe.subscribe(DiagnosticArray, "/diagnostics")
        self.outputs = {}
        if listen_to_outputs:  # so the publishing thread computes every output while mapping goes on
            for topic, latched in (("semantic_map", True), ("semantic_map/updates", False),
                                   ("semantic_map/view", True), ("semantic_map/local", False)):
                self.outputs[topic] = self.probe.subscribe(PointCloud2, f"/{topic}", latched=latched)
        self.process = start("convbki_ros.main", domain, "--ros-args", "--params-file", REPO / "config/mapper.yaml",
                             "-r", "cloud_in:=/kitti/velo/pointcloud", "-r", "odom:=/kitti/odom",
                             "-p", "device:=cpu", "-p", f"diagnostics_period:={DIAGNOSTICS_PERIOD}",
                             "-p", f"map_file:={tmp_path / 'map.npz'}", env=env)
        self.log = NodeLog(self.process)
        self.domain, self.bag = domain, bag

    def play_when_ready(self, ready_within: float) -> None:
        bag = self.bag.result()  # made while the node starts (a few seconds; the node takes longer)
        assert self.log.wait_for(r"mapper ready", timeout=ready_within), self.log.text()
        # --wait-for-inputs: the first message goes out once the node's readers have matched the
        # player's writers (a fixed grace lost the first odometry on a loaded machine).
        player = start("convbki_ros.tools.play_bag", self.domain, bag, "--wait-for-inputs")
        # The probe spins while the bag plays, so no report is lost to a full reader queue.
        assert self.probe.spin_until(lambda: player.poll() is not None, 120), "play_bag did not finish"
        output = player.communicate()[0]
        assert player.returncode == 0 and f"/kitti/velo/pointcloud {FRAMES}" in output, output
        assert "starting anyway" not in output, output
        self.reports_at_the_end = len(self.diagnostics)
        # While clouds came, the node's readers counted the player's writers on both inputs.
        during = [stats for stats in map(Stats.parse, self.diagnostics) if 0 < stats.scans_in < FRAMES]
        # (The bag holds no Path: the player did not wait for the node's reader of pose_corrections.)
        assert during and all(stats.publishers == {"cloud_in": 1, "odom": 1, "pose_corrections": 0}
                              for stats in during), during

    def reports_after_the_end(self, count: int, until) -> list[Stats]:
        """The first ``count`` reports after the bag's end, or those up to the first that ``until``
        accepts (the later ones would not change what a test reads)."""
        def after() -> list[Stats]:
            return [Stats.parse(report) for report in self.diagnostics[self.reports_at_the_end:][:count]]

        assert self.probe.spin_until(lambda: len(after()) == count or any(map(until, after())), 60), \
            "too few /diagnostics reports"
        reports = after()
        return reports[:next((n + 1 for n, stats in enumerate(reports) if until(stats)), len(reports))]

    def close(self) -> tuple[int, str]:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
        code = self.process.wait(timeout=60)
        self.probe.close()
        return code, self.log.close()


def test_a_node_without_compiled_kernels_keeps_up_with_a_bag_played_the_moment_it_is_ready(tmp_path, bag):
    cache = tmp_path / "empty-numba-cache"
    # NUMBA_DEBUG_CACHE: numba logs every kernel it compiles into the cache ("data saved").
    replay = Replay(tmp_path, bag, env={"NUMBA_CACHE_DIR": str(cache), "NUMBA_DEBUG_CACHE": "1"})
    try:
        replay.play_when_ready(ready_within=COLD_START_LIMIT)
        after = replay.reports_after_the_end(REPORTS_AFTER_THE_END, lambda stats: stats.integrated == FRAMES)
        current = [stats for stats in after if stats.integrated == FRAMES]
        assert current, f"{REPORTS_AFTER_THE_END} reports after the bag ended the node had integrated " \
                        f"{after[-1].integrated} of {FRAMES} scans: {after[-1]}"
        assert current[0].dropped == 0 and current[0].scans_in == FRAMES, current[0]
    finally:
        code, output = replay.close()
    assert code == 0, output
    warm_up = re.search(rf"compiled kernels ready in ([\d.]+) s \(cached in {re.escape(str(cache))}", output)
    assert warm_up, output
    # Every kernel was compiled before "ready", none after it, while the whole bag was mapped.
    before, _, after = output.partition("mapper ready")
    assert before.count("[cache] data saved") >= 20 and any(cache.rglob("*.nbi")), before
    assert "[cache] data saved" not in after, [line for line in after.splitlines() if "[cache] data saved" in line]


def test_under_the_workqueue_threading_layer_a_whole_replay_maps_with_every_output_watched(tmp_path, bag):
    replay = Replay(tmp_path, bag, env={"NUMBA_THREADING_LAYER": "workqueue"}, listen_to_outputs=True)
    try:
        replay.play_when_ready(ready_within=120)
        assert replay.probe.spin_until(lambda: replay.diagnostics and Stats.parse(
            replay.diagnostics[-1]).integrated == FRAMES, 60), replay.log.text()
        stats = Stats.parse(replay.diagnostics[-1])
        assert stats.dropped == 0 and replay.process.poll() is None, stats
        # The player gone, the node's readers count no publisher any more.
        assert replay.probe.spin_until(lambda: Stats.parse(replay.diagnostics[-1]).publishers == {
            "cloud_in": 0, "odom": 0, "pose_corrections": 0}, 30), Stats.parse(replay.diagnostics[-1])
        received = {topic: len(messages) for topic, messages in replay.outputs.items()}
        assert received["semantic_map/updates"] >= 2 and received["semantic_map/local"] >= 2, received
        assert received["semantic_map/view"] >= 1 and received["semantic_map"] >= 1, received
    finally:
        code, output = replay.close()
    assert code == 0, output  # a concurrent launch under workqueue aborts the process (exit code 134)
    assert "threading layer workqueue" in output, output
    assert "Terminating" not in output and "Traceback" not in output, output
