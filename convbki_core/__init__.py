"""convbki_core: Convolutional Bayesian Kernel Inference (Wilson et al., ICRA 2023).

The method only (torch, numpy, numba), no ROS. The top level follows the paper's steps:
``kernels`` (the sparse kernel), ``volume`` (window geometry and the input volume F),
``layer`` (the dense depthwise-convolution update), ``update`` (the same update as a
compiled sparse scatter), ``statistics`` (Dirichlet mean and variance), ``window`` (the
local window on a torus), ``store`` (the global map in chunks) and ``mapper`` (one object
that runs them: ``ConvBKIMapper``). ``records`` and ``shown_map`` turn the map into point
records for outputs. Beside them: ``io`` (kernel, map, PLY files, atomic writes),
``datasets`` (SemanticKITTI reader, label maps), ``training`` (the trainer), ``tools``
(the command-line front ends) and ``synth`` (the synthetic drive's simulator).

The public names below load on first use, so that a light module (the ROS side's cloud
decoder imports ``volume``) does not pull in torch.
"""

from importlib import import_module

_PUBLIC = {
    "ConvBKIKernel": "kernels", "KernelConfig": "io.kernel_file", "load_kernel_file": "io.kernel_file",
    "save_kernel_file": "io.kernel_file", "sparse_kernel": "kernels", "ConvBKILayer": "layer",
    "MapFileError": "io.map_file", "ConvBKIMapper": "mapper", "IntegrationResult": "mapper", "MapChanges": "mapper",
    "VoxelSet": "mapper", "dirichlet_statistics": "statistics",
}
__all__ = sorted(_PUBLIC)
__version__ = "0.1.0"


def __getattr__(name: str):
    if name in _PUBLIC:
        return getattr(import_module(f"convbki_core.{_PUBLIC[name]}"), name)
    raise AttributeError(f"module 'convbki_core' has no attribute {name!r}")
