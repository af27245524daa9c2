"""What empties space: free space from the rays, clamping and the movers' rules.

The paper's update only adds evidence where points land. A robot on a road with traffic also
needs the space the beams cross to read empty and the voxels a car left to be emptied:
``update`` adds the rays' counts to class 0 (the free-space update, ``FREE_CLASS``), from the
rays ``scan_rays`` casts (one per voxel of returns, and where the rays to returns beyond the
window leave it), counted by ``ray_walk`` (the Amanatides-Woo walk, compiled and its numpy
reference; ``device_rays`` does the same walk on a torch device); ``ground`` marks the
ground's surface, which the rays leave; ``clamping`` keeps changed voxels updatable;
``forgetting`` holds the movers' rules (a movable class that the rays contradict or that
nothing supports), run on a host window by ``host_forgetting`` (numpy and compiled) and on a
torch device by ``device_forgetting``; and ``present_movers`` keeps points marked as moving
out of the map. Imports ``geometry`` and ``memory``.
"""
