"""Which class-probability rows are evidence: numpy only, shared by the voxelisers and the
ROS side's PointCloud2 decoder (which must not load torch to read a cloud)."""

from __future__ import annotations

import numpy as np


def bad_probability_rows(probabilities: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows of (N, C) class ``probabilities`` that are no evidence, as three disjoint (N,) bool masks:
    rows holding a NaN/inf; finite rows holding a negative value; finite non-negative rows
    summing to zero (all zero)."""
    # Each row's minimum and maximum (with 0) find all three: NaN propagates through both,
    # -inf shows in the minimum and +inf in the maximum, and a non-negative row sums to zero
    # exactly when its maximum is zero. Column by column, because numpy reduces a short
    # inner axis (C classes) one row at a time, far slower than elementwise passes over N.
    lowest = np.zeros(probabilities.shape[0], probabilities.dtype)
    highest = np.zeros(probabilities.shape[0], probabilities.dtype)
    for column in probabilities.T:
        np.minimum(lowest, column, out=lowest)
        np.maximum(highest, column, out=highest)
    non_finite = ~(np.isfinite(lowest) & np.isfinite(highest))
    negative = ~non_finite & (lowest < 0)
    zero_sum = ~non_finite & ~negative & (highest <= 0)
    return non_finite, negative, zero_sum
