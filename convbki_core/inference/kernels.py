"""Sparse kernels and the ConvBKI filters built from them (paper Eqs. 5-7).

The sparse kernel of Melkumyan and Ramos, with signal variance sigma_0 = 1 so that the
BKI requirements k(x, x) = 1 and 0 <= k <= 1 hold:

    k(d; l) = 1/3 (2 + cos(2 pi d / l)) (1 - d / l) + 1/(2 pi) sin(2 pi d / l)   for d < l
    k(d; l) = 0                                                                  otherwise

Three variants share one module, ``ConvBKIKernel``:

* ``single``    one length for every class (S-BKI when untrained),
* ``per_class`` one spherical length per class,
* ``compound``  per class, the product of a horizontal kernel k_h(|dxy|; l_h) and a
  vertical kernel k_v(|dz|; l_z), which lets poles stretch up and roads stretch sideways.

Lengths are torch Parameters so mapping and training run the same code. They are kept
positive by clamping at ``MIN_ELL`` when the filter is built (and by the trainer after
each optimiser step). A length at or below one voxel leaves only the centre tap non-zero,
which is the identity filter: that class is counted in its own voxel and never spread.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

# The kernel file (KernelConfig and its reading and writing) is in ``io.kernel_file``; these
# names stay importable from here.
from convbki_core.io.kernel_file import (  # noqa: F401
    KERNEL_KINDS,
    KernelConfig,
    KernelFileError,
    kernel_config_from_dict,
    kernel_config_to_dict,
    load_kernel_file,
    parse_kernel_text,
    save_kernel_file,
)

# Lengths are clamped here before use: keeps d / l finite and the kernel well defined.
MIN_ELL = 1e-4
SUPPORT_TOLERANCE = 1e-6
# Filter taps below this weight are zero. Near the end of its support the kernel falls off
# as (1 - d/l)^3; a tap of 1e-9 would add evidence far below the float32 resolution of a
# concentration (the prior is ~1e-3) yet create a map voxel with no usable class. 1e-6 of a
# point is the smallest evidence that counts.
MIN_TAP_WEIGHT = 1e-6


def sparse_kernel(distance: torch.Tensor, ell: torch.Tensor) -> torch.Tensor:
    """Sparse kernel k(d; l), elementwise with broadcasting. Differentiable in ``ell``.

    ``distance`` and ``ell`` in metres; returns values in [0, 1], exactly 1 at d = 0 and
    exactly 0 for d >= l.
    """
    ell = ell.clamp_min(MIN_ELL)
    # The support ends a hair (1e-6 relative) before l so that a float32 length equal to a
    # tap distance (l = 0.2 m at 0.2 m voxels) counts as "at" it: k is ~1e-18 there anyway.
    inside = distance < ell * (1.0 - SUPPORT_TOLERANCE)
    # Clamp the ratio so that taps outside the support produce finite values (and zero
    # gradients) instead of NaN when they are masked out below.
    ratio = torch.where(inside, distance / ell, torch.ones_like(distance / ell))
    two_pi_r = 2.0 * math.pi * ratio
    value = (2.0 + torch.cos(two_pi_r)) * (1.0 - ratio) / 3.0 + torch.sin(two_pi_r) / (2.0 * math.pi)
    # Rounding can leave a value of order 1e-8 below zero just inside the support.
    return torch.where(inside, value.clamp(0.0, 1.0), torch.zeros_like(value))


class ConvBKIKernel(torch.nn.Module):
    """Learnable sparse-kernel filters K[C, 1, f, f, f] for the depthwise ConvBKI update."""

    def __init__(self, kind: str = "compound", num_classes: int = 20, filter_size: int = 5,
                 resolution: float = 0.2, ell: float | Sequence[float] = 0.5,
                 ell_h: float | Sequence[float] | None = None, ell_z: float | Sequence[float] | None = None,
                 free_ell: float | None = None, temperature: float | None = None):
        super().__init__()
        if kind not in KERNEL_KINDS:
            raise ValueError(f"kernel kind must be one of {KERNEL_KINDS}, got {kind!r}")
        if filter_size < 1 or filter_size % 2 == 0:
            raise ValueError(f"filter_size must be a positive odd integer, got {filter_size}")
        self.kind = kind
        self.num_classes = int(num_classes)
        self.filter_size = int(filter_size)
        self.resolution = float(resolution)

        def lengths(value, count: int) -> torch.nn.Parameter:
            tensor = torch.as_tensor(value, dtype=torch.float32).flatten()
            if tensor.numel() == 1:
                tensor = tensor.expand(count)
            if tensor.numel() != count:
                raise ValueError(f"expected {count} kernel lengths, got {tensor.numel()}")
            return torch.nn.Parameter(tensor.clone())

        if kind == "single":
            self.ell = lengths(ell, 1)
        elif kind == "per_class":
            self.ell = lengths(ell, self.num_classes)
        else:
            self.ell_h = lengths(ell if ell_h is None else ell_h, self.num_classes)
            self.ell_z = lengths(ell if ell_z is None else ell_z, self.num_classes)
        # The free-space category's spherical length (0: one voxel, the evidence stays where the
        # rays passed). Kept as a Parameter so that training can learn it like the class lengths.
        self.free_ell = torch.nn.Parameter(torch.tensor(0.0 if free_ell is None else float(free_ell)))
        # The temperature of probability inputs (kernel file ``temperature``; None: 1). Not a
        # length and not a Parameter: the trainer fits it by a search on validation frames.
        self.temperature = None if temperature is None else float(temperature)

    @classmethod
    def from_config(cls, config: KernelConfig) -> ConvBKIKernel:
        config.validate()
        if config.kernel == "compound":
            return cls("compound", config.num_classes, config.filter_size, config.resolution,
                       ell_h=config.ell_h, ell_z=config.ell_z, free_ell=config.free_ell,
                       temperature=config.temperature)
        return cls(config.kernel, config.num_classes, config.filter_size, config.resolution, ell=config.ell,
                   free_ell=config.free_ell, temperature=config.temperature)

    def to_config(self) -> KernelConfig:
        def values(parameter: torch.Tensor) -> list[float]:
            return [float(v) for v in parameter.detach().clamp_min(MIN_ELL).cpu()]

        config = KernelConfig(self.kind, self.resolution, self.filter_size, self.num_classes)
        if self.kind == "compound":
            config.ell_h, config.ell_z = values(self.ell_h), values(self.ell_z)
        else:
            config.ell = values(self.ell)
        free_ell = float(self.free_ell.detach())
        config.free_ell = free_ell if free_ell > MIN_ELL else None
        config.temperature = self.temperature
        return config

    @torch.no_grad()
    def clamp_lengths_(self) -> None:
        """Keep every length positive in place (the trainer calls this after each step)."""
        for parameter in self.parameters():
            parameter.clamp_(min=MIN_ELL)

    def filters(self) -> torch.Tensor:
        """The depthwise filters K[C, 1, f, f, f] (paper Eq. 6), differentiable in the lengths.

        Evaluated in float64 and returned in the parameters' dtype: near the end of its
        support the kernel is a difference of two nearly equal terms, and float32 would
        lose about three digits there. Tap distances come from integer offsets, so the
        filters are exactly symmetric.
        """
        parameter = next(self.parameters())
        half = self.filter_size // 2
        steps = torch.arange(-half, half + 1, dtype=torch.float64, device=parameter.device)
        i, j, m = torch.meshgrid(steps, steps, steps, indexing="ij")
        shape = (-1, 1, 1, 1)
        if self.kind == "compound":
            horizontal = sparse_kernel(self.resolution * torch.sqrt(i * i + j * j), self.ell_h.double().view(shape))
            vertical = sparse_kernel(self.resolution * m.abs(), self.ell_z.double().view(shape))
            weights = horizontal * vertical
        else:
            distance = self.resolution * torch.sqrt(i * i + j * j + m * m)
            weights = sparse_kernel(distance, self.ell.double().view(shape))
            if self.kind == "single":
                weights = weights.expand(self.num_classes, -1, -1, -1)
        weights = weights * (weights >= MIN_TAP_WEIGHT)  # the mask is constant: gradients pass unchanged
        return weights.unsqueeze(1).to(parameter.dtype).contiguous()

    def free_filter(self) -> torch.Tensor:
        """The free-space filter (f, f, f): the sparse kernel of ``free_ell`` over the taps'
        distances, the same floor as ``filters``. With a length of one voxel or less only the
        centre tap (weight 1) is non-zero."""
        half = self.filter_size // 2
        steps = torch.arange(-half, half + 1, dtype=torch.float64, device=self.free_ell.device)
        i, j, m = torch.meshgrid(steps, steps, steps, indexing="ij")
        distance = self.resolution * torch.sqrt(i * i + j * j + m * m)
        weights = sparse_kernel(distance, self.free_ell.double().clamp_min(MIN_ELL))
        weights = weights * (weights >= MIN_TAP_WEIGHT)
        return weights.to(self.free_ell.dtype).contiguous()

    def extra_repr(self) -> str:
        return (f"kind={self.kind}, num_classes={self.num_classes}, filter_size={self.filter_size}, "
                f"resolution={self.resolution}")
