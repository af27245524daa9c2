"""The map as point records for outputs: a voxel's centre, colour, class, variance and
probability, computed in one pass (``records``) and kept chunk by chunk from the map's changes
(``shown_map``), so that publishing a large map does not redo unchanged voxels. Imports
``geometry``, ``memory`` and ``inference`` (the Dirichlet statistics).
"""
