"""The movers' rules on a torch device window: the host rules (``host_forgetting``) as whole-window
tensor operations, with the same decisions (the rules and why: ``forgetting``'s docstring).
"""

from __future__ import annotations

import numpy as np
import torch

from convbki_core.free_space.host_forgetting import EMPTY_SHARE, FREE_CLASS, _occupied_sum
from convbki_core.memory.window import CHANGED, EVIDENCE, TOUCHED


def _contradicted_torch(alpha, physical, seen, movable, prior) -> int:
    index = torch.as_tensor(physical, device=alpha.device)
    x, y, z = index[:, 0], index[:, 1], index[:, 2]
    occupied = alpha[1:, x, y, z]
    held = occupied.argmax(dim=0) + 1
    limit = float(np.float32(prior) * np.float32(occupied.shape[0]) * np.float32(1 + 1e-6))
    has_evidence = _occupied_sum(occupied) > limit
    seen_t = torch.as_tensor(seen, device=alpha.device)
    reset = torch.as_tensor(movable, device=alpha.device)[held] & has_evidence & (seen_t != held)
    alpha[1:, x, y, z] = torch.where(reset, float(prior), occupied)  # no read of the device before the end
    return int(torch.count_nonzero(reset))


def _unsupported_torch(alpha, mask, origin, movable, prior, near, min_empty) -> int:
    """The rule of 2 over every column of a device window at once (whole-window operations, no
    loop over its layers). Each layer's decision reads only what the layers under it were
    before the rule changed anything, so the walk up a column becomes two scans along z: the
    empty voxels met since the last static one are a running count less its value where that
    static voxel stands; a voxel stands on the ground where the one under it is static."""
    size_z = mask.shape[2]
    device = alpha.device
    evident = (mask & EVIDENCE) != 0
    rest = _occupied_sum(alpha[1:])
    free = alpha[FREE_CLASS]
    empty = evident & (free > EMPTY_SHARE * (free + rest))
    best, held = alpha[1:].max(dim=0)
    is_movable = evident & ~empty & torch.as_tensor(movable, device=device)[held + 1] & (best > prior)
    static = evident & ~empty & ~is_movable
    # Along each column from its bottom layer (the torus turned), then back.
    layer = torch.arange(size_z, device=device)
    up, down = (layer + int(origin[2])) % size_z, (layer - int(origin[2])) % size_z
    static_up, empties = static[:, :, up], empty[:, :, up].to(torch.int64)
    under = torch.cumsum(empties, dim=2) - empties  # empty voxels below each layer
    last_static = torch.cummax(torch.where(static_up, layer, -1), dim=2).values
    below = torch.nn.functional.pad(last_static[:, :, :-1], (1, 0), value=-1)  # the last static one under it
    empty_below = (under - torch.gather(under, 2, below + 1))[:, :, down]
    on_ground = torch.nn.functional.pad(static_up[:, :, :-1], (1, 0), value=False)[:, :, down]
    touched = (mask & TOUCHED) != 0
    trail = is_movable & (empty_below >= min_empty) & ~touched
    fringe = is_movable & ~trail & on_ground & ~near[:, :, None] & touched
    mask &= ~(fringe.to(torch.uint8) * TOUCHED)
    mask |= trail.to(torch.uint8) * CHANGED
    alpha[FREE_CLASS] = torch.where(trail, torch.maximum(free, rest + 1.0), free)
    return int(torch.count_nonzero(trail))
