"""convbki_core: Convolutional Bayesian Kernel Inference (Wilson et al., ICRA 2023).

The method only (torch + numpy), no ROS. Modules follow the paper:
``kernels`` (sparse kernel, Eqs. 5-7), ``voxelize`` (input volume, Eq. 3), ``layer``
(depthwise-convolution update, Eq. 4), ``statistics`` (Dirichlet mean and variance,
Eq. 2), ``store`` and ``mapper`` (global mapping), ``mapfile`` and ``ply`` (files).
"""

from convbki_core.kernels import ConvBKIKernel, KernelConfig, load_kernel_file, save_kernel_file, sparse_kernel
from convbki_core.layer import ConvBKILayer
from convbki_core.mapfile import MapFileError
from convbki_core.mapper import ConvBKIMapper, IntegrationResult, VoxelSet
from convbki_core.statistics import dirichlet_statistics

__all__ = ["ConvBKIKernel", "ConvBKILayer", "ConvBKIMapper", "IntegrationResult", "KernelConfig", "MapFileError",
           "VoxelSet", "dirichlet_statistics", "load_kernel_file", "save_kernel_file", "sparse_kernel"]
__version__ = "0.1.0"
