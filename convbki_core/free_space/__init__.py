"""What empties space: free space from the rays, clamping and the movers' rules.

The paper's update only adds evidence where points land. A robot on a road with traffic also
needs the space the beams cross to read empty and the voxels a car left to be emptied:
``rays`` walks each return's beam through the window (and ``device_rays`` does the same walk
on a torch device), ``clamping`` keeps changed voxels updatable, ``forgetting`` holds the
movers' rules (a movable class that the rays contradict or that nothing supports), and
``present_movers`` keeps points marked as moving out of the map. Imports ``geometry`` and
``memory``.
"""
