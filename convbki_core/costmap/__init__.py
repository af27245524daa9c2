"""The planner's view: a 2D traversability costmap computed from the 3D map's columns.

``profile`` holds the traversability profile (what a class costs a robot, its ground classes,
its height band); ``columns`` the cost of a column of voxels (the classes' expected
probabilities and variances, the hidden ground under cars) over voxels given as a list;
``grid`` the cost grid and its rolling region; ``window_pass`` the same grid read in place from
the window in one compiled pass, and ``device`` on a torch device. Imports ``memory``.
"""
