"""Synthetic SemanticKITTI-format drives: a procedural street, a simulated 64-beam LiDAR and
a segmentation-noise model that imitates a real network's errors.

Modules: ``scene`` (streets, buildings, vegetation, vehicles, people as ray-castable
primitives), ``route`` (the ego vehicle's smooth loop and its poses), ``lidar`` (numba ray
caster and geometric queries), ``noise`` (the input segmentation: persistent and per-view
errors, calibrated to a target mIoU), ``writer`` (SemanticKITTI files) and ``drive`` (the
whole generator). ``convbki_core.tools.synth`` is the command-line front end.
"""

from convbki_core.synth.drive import DriveConfig, SynthError, check_destination, generate_drive, lidar_poses

__all__ = ["DriveConfig", "SynthError", "check_destination", "generate_drive", "lidar_poses"]
