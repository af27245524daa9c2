"""The ConvBKI layer: the Bayesian update as a depthwise 3D convolution (paper Eq. 4).

    alpha_t[c] = alpha_{t-1}[c] + (F[c] * K[c])      (zero-padded, one filter per class)

This dense form is the paper's formulation, the path used on CUDA, the training path and
the reference every faster path is tested against.
"""

from __future__ import annotations

import torch
import torch.nn.functional as functional

from convbki_core.inference.kernels import ConvBKIKernel


class ConvBKILayer(torch.nn.Module):
    """Depthwise-convolution Bayesian kernel update with learnable sparse kernels."""

    def __init__(self, kernel: ConvBKIKernel):
        super().__init__()
        self.kernel = kernel

    @property
    def num_classes(self) -> int:
        return self.kernel.num_classes

    def increment(self, features: torch.Tensor) -> torch.Tensor:
        """The evidence added by input volume F: depthwise conv3d(F, K), zero padding.

        ``features`` is (C, X, Y, Z) or (B, C, X, Y, Z); the result has the same shape.
        """
        batched = features.dim() == 5
        volume = features if batched else features.unsqueeze(0)
        if volume.shape[1] != self.num_classes:
            raise ValueError(f"input volume has {volume.shape[1]} classes, the kernel {self.num_classes}")
        filters = self.kernel.filters().to(dtype=volume.dtype, device=volume.device)
        result = functional.conv3d(volume, filters, padding=self.kernel.filter_size // 2, groups=self.num_classes)
        return result if batched else result.squeeze(0)

    def forward(self, alpha_prior: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        """Posterior concentrations alpha_t = alpha_{t-1} + conv3d(F, K) (paper Eq. 4)."""
        return alpha_prior + self.increment(features)
