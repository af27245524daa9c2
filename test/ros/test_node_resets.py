"""The mapper node's resets and saves over a run, over DDS, in a separate process.

One node with the reset options on (on_pose_jump reset, reset_on_stamp_backwards) and autosave
every 1 s: clouds with no odometry at all are warned about and not mapped; autosave writes
the map when it changed; a pose jump and time going backwards reset the map, an odometry outage
keeps it; on_pose_jump new_file saves the map so far to a segment file of its own; SIGTERM saves
the map to the map_file in use.
"""

import re
import signal

from mapper_rig import SECOND, TRANSLATION, WAIT, Rig, cloud, expect_file_holds, odometry, offline_map


def test_resets_on_request_no_odometry_warnings_autosave_and_save_on_sigterm(tmp_path):
    # Short periods where the test waits for them: the warnings, clouds without odometry waiting to
    # be dropped (0.5 s each), the autosave (1 s, the shortest it takes); reports every 0.05 s.
    rig = Rig(tmp_path, "-p", "on_pose_jump:=reset", "-p", "reset_on_stamp_backwards:=true",
              "-p", "odometry_timeout:=0.5", "-p", "autosave_period:=1.0", "-p", "pose_wait_timeout:=0.5",
              diagnostics_period=0.05, wait=False)
    try:
        # What the files must hold, computed while the node starts: one scan, two, one at the pose after a jump.
        jumped = TRANSLATION + [0.0, -80.0, 0.0]
        one_scan, two_scans, one_jumped = offline_map(1), offline_map(2), offline_map(1, translation=jumped)
        rig.wait_ready()

        # Clouds and no odometry at all: a warning every odometry_timeout, and nothing mapped.
        mark = rig.log.mark()
        warning = r"\[WARN\].*no odometry at all on /odom for [\d.]+ s while clouds arrive on /cloud_in"
        sent = rig.stats().scans_in
        for _ in range(int(WAIT / 0.2)):  # clouds keep coming until the warning came twice
            if len(rig.log.find(warning, mark)) >= 2:
                break
            rig.publish(cloud(rig.next_stamp(0.1)))
            sent += 1
            # The next cloud once the node has counted this one (a /diagnostics report says so).
            rig.wait_stats(lambda s, sent=sent: s.scans_in == sent)
        assert len(rig.log.find(warning, mark)) == 2, rig.log.text(mark)
        assert rig.wait_stats(lambda s: s.level == 2).integrated == 0  # ERROR on /diagnostics
        stats = rig.wait_stats(lambda s: s.dropped == s.scans_in)
        assert stats.integrated == 0 and stats.voxels == 0 and stats.reasons.get("no pose", 0) > 0, stats

        # Autosave writes the map when it has changed (nothing was saved while it was empty).
        assert not rig.map_file.exists()
        mark = rig.log.mark()
        stats = rig.integrate_good_cloud()
        assert stats.voxels == len(one_scan)
        assert rig.probe.spin_until(rig.map_file.exists, WAIT), "autosave never wrote the map file"
        expect_file_holds(rig.map_file, one_scan)  # saves are atomic: a file that exists is complete
        rig.wait_log(rf"autosave: saved {stats.voxels} voxels to {re.escape(str(rig.map_file))}", mark)
        autosaved = rig.map_file.read_bytes()

        # A pose jump resets the map; mapping resumes at the new pose.
        mark = rig.log.mark()
        far = TRANSLATION + [0.0, 80.0, 0.0]
        rig.publish(odometry(rig.next_stamp(), translation=far))
        rig.wait_log(r"\[WARN\].*odometry jumped 80.00 m in 1.00 s .*map reset \(on_pose_jump reset\)", mark)
        assert rig.wait_stats(lambda s: s.voxels == 0).integrated == stats.integrated
        rig.map_message(0)
        assert rig.integrate_good_cloud(translation=far).voxels > 0

        # An outage (no odometry for 30 s, then a pose 80 m on) is named so, and keeps the map.
        mark = rig.log.mark()
        for _ in range(3):  # odometry at its usual pace first (one a second here)
            rig.integrate_good_cloud(translation=far)
        rig.next_stamp(29.0)
        on = far + [0.0, 80.0, 0.0]
        after_outage = rig.integrate_good_cloud(translation=on)
        rig.wait_log(r"\[WARN\].*odometry outage of 30.0 s \(none stamped between [\d.]+ s and [\d.]+ s\); the pose "
                     r"after it is 80.00 m away \(max_pose_jump = 10.0 m\): map kept", mark)
        assert after_outage.voxels > 0 and "jumped" not in rig.log.text(mark)

        # Time going backwards resets the map too.
        mark = rig.log.mark()
        rig.stamp -= 100 * SECOND
        rig.publish(odometry(rig.next_stamp()))
        rig.wait_log(r"\[WARN\].*time went backwards by 9\d\.\d+ s .*map reset \(reset_on_stamp_backwards\)", mark)
        rig.wait_stats(lambda s: s.voxels == 0)
        rig.map_message(0)
        final = rig.integrate_good_cloud()
        rig.integrate_good_cloud()
        assert final.voxels == stats.voxels

        # The resets were not a request to write the file: autosave keeps the map saved before them,
        # and /diagnostics says this map is not saved.
        unsaved = rig.wait_stats(lambda s: s.level == 1 and "not saved automatically" in s.message)
        assert "a reset when time went back" in unsaved.message, unsaved
        assert rig.map_file.read_bytes() == autosaved

        # on_pose_jump new_file: the map so far goes to a segment file (a new one, as map_file holds
        # evidence this map lacks), and the new segment's map will be saved to the next.
        assert all(result.successful for result in rig.set_parameters(on_pose_jump="new_file"))
        assert not rig.set_parameters(on_pose_jump="split")[0].successful
        mark = rig.log.mark()
        rig.publish(odometry(rig.next_stamp(), translation=jumped))
        segment, following = (rig.map_file.with_name(f"map.segment-{n}.npz") for n in (2, 3))
        rig.wait_log(rf"\[WARN\].*odometry jumped 80.00 m in 1.00 s .*the map so far \({final.voxels} voxels\) is "
                     rf"being saved to {re.escape(str(segment))}; a new map starts for the new segment, saved to "
                     rf"{re.escape(str(following))} \(map_file is now .*\(on_pose_jump new_file\)", mark)
        rig.wait_log(rf"saved the segment before the jump, {final.voxels} voxels, to {re.escape(str(segment))}", mark)
        expect_file_holds(segment, two_scans)
        assert rig.parameter("map_file") == str(following)
        assert rig.wait_stats(lambda s: s.voxels == 0).integrated == final.integrated + 1

        # SIGTERM (what a supervisor sends) saves the new segment's map to the map_file now in use:
        # autosave is turned off first, so only the save on shutdown can write it.
        assert all(result.successful for result in rig.set_parameters(autosave_period=0.0))
        last = rig.integrate_good_cloud(translation=jumped)
        autosaved_segment = following.read_bytes() if following.exists() else b""  # the segment's empty start
        rig.process.send_signal(signal.SIGTERM)
        assert rig.process.wait(timeout=WAIT) == 0
    finally:
        output = rig.close()
    assert "Traceback" not in output and "[ERROR]" not in output, output
    assert f"on shutdown: saved {last.voxels} voxels to {following}" in output, output
    assert following.read_bytes() != autosaved_segment
    expect_file_holds(following, one_jumped)
    assert rig.map_file.read_bytes() == autosaved  # the file saved before the resets was never overwritten
    expect_file_holds(rig.map_file, one_scan)
