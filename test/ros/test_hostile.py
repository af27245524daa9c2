"""Anyone on the robot's ROS domain, with no credentials, against a running mapper node.

Each attack runs from a process of its own (``test/hostile_client.py``), as another
participant on the domain would: parameters set to files outside the node's folder, to links,
to other programs' files, to names too long for the file system; parameter messages of types
and values no check foresees; resource limits raised at run time; clouds whose data lies about
their size; a Path of 300,000 poses; floods of TF frames and records and odometry; a reset or a
forgotten box followed by saves. After each: the node lives and answers its services, what it
refused is said with the reason, every file outside the maps it owns is byte for byte what it was
(no file or folder appeared), its map files hold what they must, and its memory stays bounded.
"""

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from mapper_rig import Rig
from ros_helpers import REPO

from convbki_core.io.map_file import map_file_voxels
from convbki_ros.dds import PROFILE_VARIABLES, large_data_profile

CLIENT = REPO / "test" / "hostile_client.py"
VICTIM = b"ssh-ed25519 AAAAC3NzaC1lZDI1NTE5AAAAIHostileTestKeyLine robot@host\n"
MAX_CLOUD_MEGABYTES = 5  # the node's cap in this test: the attack sends a consistent cloud above it
MAX_KEPT_MAPS = 2
MAX_PATH_POSES = 1000  # the attack's Path holds 300,000
MAX_MAP_MEGABYTES = 1.0  # a few places of the test's scene fill it
# What the node's memory may grow by over every attack: the caps (clouds, Path, TF, odometry)
# hold it far below; without them a TF flood alone kept every record.
MEMORY_GROWTH_LIMIT_MB = 400


def attack(target: "Target", name: str, *args: str, timeout: float = 120.0) -> dict:
    """Run one attack of hostile_client.py in its own process; its JSON answer."""
    return attacks(target, (name, *args), timeout=timeout)[0]


def attacks(target: "Target", *runs: tuple[str, ...], timeout: float = 120.0) -> list[dict]:
    """Run attacks of hostile_client.py side by side, each in its own process (``runs``: the
    attack's name and its arguments); their JSON answers, in order."""
    # The player's Fast DDS profile: its writers send heartbeats every 0.2 s, so the attacker
    # learns in a fraction of a second (not Fast DDS's 3 s) that the node has what it sent.
    profile = {variable: str(large_data_profile(player=True)) for variable in PROFILE_VARIABLES}
    environment = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", **profile)
    processes = []
    for name, *args in runs:
        command = [sys.executable, str(CLIENT), name, "--domain", str(target.rig.domain)]
        for arg in args:
            command += ["--arg", arg]
        processes.append(subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                          cwd=REPO, env=environment))
    answers = []
    for (name, *_), process in zip(runs, processes, strict=True):
        output, errors = process.communicate(timeout=timeout)
        assert process.returncode == 0, f"the attack {name} failed itself:\n{output}\n{errors}"
        answers.append(json.loads(output.strip().splitlines()[-1]))
    return answers


def tree(root: Path) -> dict[str, tuple]:
    """Every entry under ``root``: (kind, content hash or link target); a node's scan log folder
    as a folder only (its files change as the node maps)."""
    entries = {}
    for folder, names, files in os.walk(root):
        logs = [name for name in names if name.endswith(".scan_log")]
        names[:] = [name for name in names if name not in logs]  # os.walk does not go into them
        for name in logs:
            entries[str(Path(folder, name).relative_to(root))] = ("folder",)
        for name in names + files:
            path = Path(folder, name)
            if path.is_symlink():
                entries[str(path.relative_to(root))] = ("link", os.readlink(path))
            elif path.is_dir():
                entries[str(path.relative_to(root))] = ("folder",)
            else:
                entries[str(path.relative_to(root))] = ("file", hashlib.sha256(path.read_bytes()).hexdigest())
    return entries


def resident_megabytes(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS")


class Target:
    """The node under attack, its folder, and what lies beside and outside it."""

    def __init__(self, root: Path, folder: Path, *parameters: str):
        self.root = root
        self.outside = root / "outside"
        self.outside.mkdir()
        self.victim = self.outside / "authorized_keys"
        self.victim.write_bytes(VICTIM)
        self.folder = folder  # map_folder: maps/map.npz and shown.ply in it
        self.folder.mkdir()
        (self.folder / "notes.txt").write_bytes(b"a user's file beside the maps\n")
        (self.folder / "link.npz").symlink_to(self.victim)
        (self.folder / "link.ply").symlink_to(self.victim)
        self.rig = Rig(self.folder, *parameters, diagnostics_period=0.05)
        self.rig.integrate_good_cloud()
        for _ in range(2):  # map.npz and map.npz.prev
            assert self.rig.call("save_map").success
        assert self.rig.call("export_ply").success
        self.outside_tree = tree(self.outside)
        self.memory_before = resident_megabytes(self.rig.process.pid)

    def others(self) -> dict[str, tuple]:
        """The folder's entries that are not the node's own files (maps, their .prev, kept maps, the PLY)."""
        own = ("maps", "shown.ply")
        return {name: entry for name, entry in tree(self.folder).items() if not name.startswith(own)}

    def expect_alive(self) -> None:
        assert self.rig.process.poll() is None, self.rig.log.text()
        exported = self.rig.call("export_ply")
        assert exported.success, exported.message


@pytest.fixture(scope="module")
def target(tmp_path_factory):
    root = tmp_path_factory.mktemp("hostile")
    target = Target(root, root / "robot", "-p", f"map_folder:={root / 'robot'}",
                    "-p", f"max_cloud_megabytes:={MAX_CLOUD_MEGABYTES}", "-p", f"max_kept_maps:={MAX_KEPT_MAPS}",
                    "-p", f"max_path_poses:={MAX_PATH_POSES}", "-p", f"max_map_megabytes:={MAX_MAP_MEGABYTES}")
    others = target.others()
    try:
        yield target
        target.expect_alive()
        assert tree(target.outside) == target.outside_tree, "a file outside the node's folder changed"
        assert target.others() == others, "a file in the node's folder that is not its own changed"
        growth = resident_megabytes(target.rig.process.pid) - target.memory_before
        assert growth < MEMORY_GROWTH_LIMIT_MB, f"the node's memory grew by {growth:.0f} MB"
    finally:
        output = target.rig.close()
    assert "Traceback" not in output, output


def test_no_request_writes_outside_the_folder_or_over_a_file_that_is_not_the_nodes(target):
    """map_file and ply_file set to a file outside the folder (absolute and by ../), a user's
    file in it, a link to the victim, a name in a folder that does not exist: each refused with
    its reason, the parameter unchanged, and the save or export after it writes the node's own
    file, nothing else."""
    rig = target.rig
    map_file, ply_file = rig.parameter("map_file"), rig.parameter("ply_file")
    values = {str(target.victim): "outside the folder", "../outside/authorized_keys": "outside the folder",
              "notes.txt": "not a ConvBKI map file|not a PLY file of this node", "link.npz": "is a link",
              "link.ply": "is a link", "new/sub/map.npz": "does not exist", "/": "outside the folder|not a file"}
    results = attack(target, "files", *values)
    for name in ("map_file", "ply_file"):
        for value, why in values.items():
            result = results[f"{name}={value!r}"]
            assert result["set"]["answered"] and not result["set"]["successful"], (name, value, result)
            assert any(w in result["set"]["reason"] for w in why.split("|")), (name, value, result["set"]["reason"])
            assert result["then"]["success"], (name, value, result["then"])  # the node's own file, written
    assert (rig.parameter("map_file"), rig.parameter("ply_file")) == (map_file, ply_file)
    assert target.victim.read_bytes() == VICTIM and not (target.folder / "new").exists()
    assert map_file_voxels(map_file) > 0


def test_parameter_requests_no_check_foresees_are_refused_and_the_node_lives(target):
    """A 300-character path (which once ended the node), a NUL byte, a type id that does not
    exist, resource limits raised at run time (read-only), a nanosecond autosave, the clock handed
    to /clock: each answered, none applied."""
    rig = target.rig
    results = attack(target, "weird_parameters")
    for what, result in results.items():
        if what == "NUL in map_file" and not result["answered"]:
            continue  # rclpy would not even send it
        assert result["answered"] and not result["successful"], (what, result)
    for name in ("cloud_queue_megabytes", "cloud_queue_size", "view_max_points", "costmap_max_cells",
                 "max_map_megabytes", "map_folder"):
        assert "read-only" in results[name]["reason"] or "read only" in results[name]["reason"], results[name]
    assert "too often" in results["autosave_period"]["reason"]
    assert "read at start only" in results["use_sim_time"]["reason"]  # else anyone could drive its clock
    assert rig.parameter("cloud_queue_megabytes") == 1024.0 and rig.parameter("autosave_period") == 0.0
    target.expect_alive()


def test_inputs_over_their_caps_are_refused_before_they_cost(target):
    """A cloud claiming one point and carrying 2 MB, one over max_cloud_megabytes, one with a
    frame id of 100,000 characters; a Path of 300,000 poses (over max_path_poses, refused before
    it is decoded, and a service answered right after); 3,000 TF frames and 20,000 records of
    one frame; odometry with a 100,000-character frame id. Each refusal counted, the map unchanged.
    (The counts that bound the TF and odometry histories: test_tf_buffer.py, test_pose_buffer.py.)"""
    rig = target.rig
    before = rig.stats()
    mark = rig.log.mark()
    clouds, flood, tf, odometry = attacks(target, ("cloud_lies", str(MAX_CLOUD_MEGABYTES + 3)),
                                          ("path_flood", "300000"), ("tf_flood", "3000", "20000"), ("odometry_lies",))
    assert clouds["acknowledged"] and tf["acknowledged"] and odometry["acknowledged"], (clouds, tf, odometry)
    assert flood["acknowledged"] and flood["then"]["success"], flood
    after = rig.wait_stats(lambda s: s.scans_in >= before.scans_in + 3 and s.odometry_in >= before.odometry_in + 1)
    assert after.reasons.get("bad cloud", 0) - before.reasons.get("bad cloud", 0) == 2, after
    assert after.reasons.get("too large", 0) - before.reasons.get("too large", 0) == 1, after
    assert after.odometry_rejected == before.odometry_rejected + 1, after
    rig.wait_log(rf"Path on .*pose_corrections.*300000 poses are more than max_path_poses = {MAX_PATH_POSES}", mark)
    rig.wait_log(r"1000 frames are known already", mark)
    assert (after.integrated, after.voxels, after.map_version) == (before.integrated, before.voxels,
                                                                   before.map_version)
    target.expect_alive()


def test_resets_and_forgotten_boxes_followed_by_saves_never_lose_the_last_map(target):
    """~/reset then two saves: map_file and .prev hold the empty map, the map they replaced is
    kept whole as map.npz.kept-<time>; the same after a forgotten box; a third loss is refused
    (max_kept_maps) and leaves every file as it was."""
    rig = target.rig
    map_file = Path(rig.parameter("map_file"))
    full = map_file.read_bytes()
    answers = attack(target, "trigger", "reset", "save_map", "save_map")
    assert all(answer["success"] for answer in answers.values()), answers
    assert "is kept as map.npz.kept-" in answers["1: save_map"]["message"], answers
    kept = sorted(map_file.parent.glob("map.npz.kept-*"))
    assert len(kept) == 1 and kept[0].read_bytes() == full
    assert map_file_voxels(map_file) == 0 and map_file_voxels(f"{map_file}.prev") == 0
    assert oct(kept[0].stat().st_mode & 0o777) == oct(0o600)

    rig.integrate_good_cloud()
    assert rig.call("save_map").success
    second = map_file.read_bytes()
    assert all(r.successful for r in rig.set_parameters(clear_box_min=[-1e4] * 3, clear_box_max=[1e4] * 3))
    answers = attack(target, "trigger", "clear_box", "save_map", "save_map")
    assert all(answer["success"] for answer in answers.values()), answers
    kept = sorted(map_file.parent.glob("map.npz.kept-*"))
    assert len(kept) == 2 and any(k.read_bytes() == second for k in kept)

    rig.integrate_good_cloud()
    assert rig.call("save_map").success
    files_before = tree(map_file.parent)
    answers = attack(target, "trigger", "reset", "save_map")
    assert not answers["1: save_map"]["success"] and "max_kept_maps = 2" in answers["1: save_map"]["message"]
    assert tree(map_file.parent) == files_before and map_file_voxels(map_file) > 0


def test_odometry_over_new_ground_fills_the_map_to_its_bound_and_mapping_goes_on(target):
    """Spoofed odometry taking the robot to 8 places 100 m apart, a cloud at each: the map fills
    max_map_megabytes, says so (one warning, WARN on /diagnostics) and stops growing, under the
    ceiling, while each cloud is still integrated in the window."""
    rig = target.rig
    before = rig.stats()
    mark = rig.log.mark()
    assert attack(target, "drive", "8") == {"places": 8}
    after = rig.wait_stats(lambda s: s.integrated >= before.integrated + 8)
    values = {item.key: item.value for item in rig.diagnostics[-1].status[0].values}
    assert values["map_full"] == "true" and int(values["map_voxels_dropped"]) > 0, values
    assert float(values["map_megabytes"]) <= 1.25 * MAX_MAP_MEGABYTES, values
    assert after.level >= 1 and "map full (max_map_megabytes 1)" in after.message, after
    assert len(rig.wait_log(r"\[WARN\].*the map is full: \d+ MB of voxels reached max_map_megabytes = 1", mark)) == 1
