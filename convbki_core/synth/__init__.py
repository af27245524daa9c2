"""Synthetic SemanticKITTI-format drives: a procedural street, a simulated 64-beam LiDAR and
a segmentation-noise model that imitates a real network's errors.

Modules: ``scene`` (the static world as ray-castable primitives, from ``streets``: street grid,
route, ground raster, sidewalks; ``furnish``: buildings, vegetation, street furniture, parked
vehicles, people; ``objects`` and ``primitives``: the shapes), ``route`` (the ego vehicle's
smooth loop and its poses), ``traffic`` and ``movers`` (optional moving road users: where they
go, their shapes and ray casting, the ``movers.json`` sidecar; ``traffic_planner``,
``traffic_varied`` and ``traffic_geometry``: the planner, its classic and varied behaviours'
candidates and the street geometry they share), ``lidar`` (numba ray caster and
geometric queries), ``noise`` (the input segmentation: persistent and per-view errors,
calibrated to a target mIoU), ``writer`` (SemanticKITTI files) and ``drive`` (the whole
generator: ``drive.generate_drive``). ``convbki_core.tools.synth`` is the command-line front end.
"""
