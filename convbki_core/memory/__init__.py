"""The map's memory: the resident window around the sensor and the global store behind it.

The paper fetches a local window from a global key/value map before each update and writes it
back after. Here ``window.RollingWindow`` keeps the window resident on a torus (only the slabs
the sensor drives into are fetched), ``column_classes`` keeps the bits of the classes each of
its columns holds (so readers of every column skip the runs at the prior), ``store.VoxelStore``
keeps every voxel with evidence in chunks, and ``compact_rows`` packs a voxel's concentrations
to the classes it holds. Imports ``geometry`` only.
"""
