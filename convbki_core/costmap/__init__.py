"""The planner's view: a 2D traversability costmap computed from the 3D map's columns.

``columns`` holds the traversability profile and the cost of a column of voxels (the classes'
expected probabilities and variances, the hidden ground under cars), the grid of a window and
its rolling region; ``device`` computes the same grid on a torch device. Imports ``memory``.
"""
