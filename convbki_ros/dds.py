"""DDS settings for large point clouds.

With Fast DDS's default socket buffers (the system default, about 200 KB), a 3-4 MB
PointCloud2 overflows the receiver's buffer and the small messages that arrive with it
(odometry) are lost until the next heartbeat repairs them, seconds later: the mapper then
sees clouds without poses. The package ships a Fast DDS profile with a large shared-memory
segment and 4 MB UDP buffers; the package's own processes use it unless the user chose a
profile or another middleware.

Fast DDS 2.x (ROS 2 Jazzy's) reads the profile named by ``FASTRTPS_DEFAULT_PROFILES_FILE``;
Fast DDS 3.x renamed the variable ``FASTDDS_DEFAULT_PROFILES_FILE``. Both are set, and a
profile the user named in either is left alone.
"""

from __future__ import annotations

import os
from pathlib import Path

from convbki_core.paths import config_dir

# The variable Fast DDS 2.x reads first, then the one of Fast DDS 3.x.
PROFILE_VARIABLES = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")


def large_data_profile(player: bool = False) -> Path:
    """The shipped profile; ``player``: the one for a source that may be paused (``play_bag``)."""
    return config_dir() / "dds" / ("fastdds_player.xml" if player else "fastdds_large_data.xml")


def use_large_data_profile(player: bool = False) -> str | None:
    """Point Fast DDS at the shipped profile (before rclpy.init); returns the profile used, if any.

    ``player``: the profile of ``play_bag``, whose participants announce a lease of 5 minutes
    instead of Fast DDS's 20 s, so that subscribers do not forget a player stopped for a while
    (SIGSTOP, Ctrl-Z, a stalled machine) and lose what it sends when it resumes.
    """
    if any(os.environ.get(variable) for variable in PROFILE_VARIABLES):
        return None
    middleware = os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    profile = large_data_profile(player)
    if not middleware.startswith("rmw_fastrtps") or not profile.is_file():
        return None
    for variable in PROFILE_VARIABLES:
        os.environ[variable] = str(profile)
    return str(profile)


PUBLICATION_MODE_VARIABLE = "RMW_FASTRTPS_PUBLICATION_MODE"


def publish_asynchronously() -> bool:
    """Let Fast DDS send this process's messages from its own thread (before rclpy.init).

    Recent rmw_fastrtps publishes synchronously: ``publish()`` returns only once a message
    is sent, and rclpy holds the GIL all along. For the mapper's ``/semantic_map`` (100 MB
    for a map of 3.7 M voxels) that stalled the update thread for up to a second, long
    enough to fill the cloud queue at 10 Hz. Asynchronous publication queues the message
    and returns. Returns False when the user chose a mode or another middleware.
    """
    if os.environ.get(PUBLICATION_MODE_VARIABLE):
        return False
    if not os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp").startswith("rmw_fastrtps"):
        return False
    os.environ[PUBLICATION_MODE_VARIABLE] = "ASYNCHRONOUS"
    return True
