"""convbki_core: Convolutional Bayesian Kernel Inference (Wilson et al., ICRA 2023).

The method only (torch, numpy, numba), no ROS. Its stages are packages, each importing only
the ones before it in this list:

* ``geometry``: the voxel grid, the input volume F (Eq. 3), poses;
* ``memory``: the resident window on a torus and the global store;
* ``correction``: the scan log and the exact replay a SLAM's corrections need;
* ``io``: kernel, map, PLY and label-map files, atomic writes;
* ``inference``: the kernel (Eq. 5), the update (Eq. 4) as the paper's convolution and as a
  compiled sparse scatter, the Dirichlet statistics (Eq. 2);
* ``free_space``: rays, clamping and the movers' rules;
* ``costmap``: the planner's 2D costmap from the map's columns;
* ``outputs``: the map as point records for outputs;
* ``torch_path``: the whole window on a torch device;
* ``measures``: mIoU, calibration, trails, the costmap's and a correction's scores.

At the top: ``mapper`` (``ConvBKIMapper``, which composes the stages), ``map_contents``
(the mapper's queries: reading the map and its changes), ``config`` (``MapperConfig``),
``parts`` (the parts a configuration builds), ``offline`` (mapping drives
without ROS), ``warm_up`` (the compiled kernels' cache) and the plumbing (``compiled``,
``devices``, ``paths``). Beside them: ``datasets`` (SemanticKITTI and drift drives),
``synth`` (the synthetic drive's simulator), ``training`` and ``tools`` (the programs).

The public names below load on first use, so that a light module (the ROS side's cloud
decoder imports ``geometry.volume``) does not pull in torch.
"""

from importlib import import_module

_PUBLIC = {
    "ConvBKIKernel": "inference.kernels", "KernelConfig": "io.kernel_file", "load_kernel_file": "io.kernel_file",
    "save_kernel_file": "io.kernel_file", "sparse_kernel": "inference.kernels", "ConvBKILayer": "inference.layer",
    "MapFileError": "io.map_file", "ConvBKIMapper": "mapper", "IntegrationResult": "mapper",
    "MapChanges": "map_contents", "VoxelSet": "map_contents", "dirichlet_statistics": "inference.statistics",
}
__all__ = sorted(_PUBLIC)
__version__ = "0.1.0"


def __getattr__(name: str):
    if name in _PUBLIC:
        return getattr(import_module(f"convbki_core.{_PUBLIC[name]}"), name)
    raise AttributeError(f"module 'convbki_core' has no attribute {name!r}")
