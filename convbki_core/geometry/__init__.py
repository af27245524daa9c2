"""The map's geometry: the voxel grid, the local window's box and the input volume F (paper
Eq. 3), and the pose math.

The lowest stage: it imports only the plumbing (``compiled``). ``grid`` holds the window's
geometry, the voxel index helpers, the pose check and the point transform; ``volume`` turns a
labelled scan into the sparse input volume of the window it falls in; ``poses`` holds
quaternions, 4x4 poses and their interpolation, shared by the method and the ROS side.
"""
