"""Following a SLAM's corrections: the scan log and the exact replay.

ConvBKI's update is a sum (paper Eq. 4), so scans integrated long ago can be mapped again at
the poses a SLAM moved them to. ``scan_log`` keeps what that needs (each scan's voxels and a
base map before the oldest); ``replay`` runs the replay on a mapper it is given, and
``map_corrections`` is the mapper's side of it (a mixin: the log's bases, the plan, the
corrected map). Imports ``geometry`` and ``memory`` only.
"""
