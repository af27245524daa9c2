"""convbki_core: Convolutional Bayesian Kernel Inference (Wilson et al., ICRA 2023).

The method only (torch + numpy), no ROS. Modules follow the paper:
``kernels`` (sparse kernel, Eqs. 5-7), ``voxelize`` (input volume, Eq. 3), ``layer``
(depthwise-convolution update, Eq. 4), ``statistics`` (Dirichlet mean and variance,
Eq. 2), ``store`` and ``mapper`` (global mapping), ``mapfile`` and ``ply`` (files).

The public names below load on first use, so that a light module (the PointCloud2 codec's
``probabilities``) does not pull in torch.
"""

from importlib import import_module

_PUBLIC = {
    "ConvBKIKernel": "kernels", "KernelConfig": "kernels", "load_kernel_file": "kernels",
    "save_kernel_file": "kernels", "sparse_kernel": "kernels", "ConvBKILayer": "layer",
    "MapFileError": "mapfile", "ConvBKIMapper": "mapper", "IntegrationResult": "mapper", "MapChanges": "mapper",
    "VoxelSet": "mapper", "dirichlet_statistics": "statistics",
}
__all__ = sorted(_PUBLIC)
__version__ = "0.1.0"


def __getattr__(name: str):
    if name in _PUBLIC:
        return getattr(import_module(f"convbki_core.{_PUBLIC[name]}"), name)
    raise AttributeError(f"module 'convbki_core' has no attribute {name!r}")
