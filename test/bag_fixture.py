"""The bag tests' data (test/ros/test_bags_*.py): the stamps and cloud sizes of the 4-frame
sequence 08 that their ``dataset`` fixture (test/ros/conftest.py) writes, and kitti_to_bag called
as a function."""

from convbki_ros.tools import kitti_to_bag

EPOCH_NS = 1_700_000_000_000_000_000
TIMES = [0.0, 0.1037, 0.2071, 0.3109]
FRAME_SIZES = [300, 301, 280, 333]


def convert(*argv: str) -> int:
    return kitti_to_bag.main([str(a) for a in argv])
