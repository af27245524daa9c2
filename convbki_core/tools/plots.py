"""Pictures of maps and kernels (matplotlib, written to PNG files atomically)."""

from __future__ import annotations

import io
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from convbki_core.io.atomic import atomic_write_bytes
from convbki_core.io.labels import LabelMap

if TYPE_CHECKING:
    from convbki_core.inference.kernels import ConvBKIKernel
    from convbki_core.map_contents import VoxelSet


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")  # files only, no display needed
    import matplotlib.pyplot as plt

    return plt


def _save(figure, path: str | Path) -> None:
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=110, bbox_inches="tight")
    _pyplot().close(figure)
    atomic_write_bytes(Path(path), buffer.getvalue())


def birds_eye_rasters(voxels: VoxelSet, colours: np.ndarray, resolution: float, max_pixels: int = 2500):
    """Top-down rasters: per (x, y) column, the voxel holding the most evidence.

    The kernel spreads some evidence above and below every surface; the plain top voxel
    of a column would show that fringe (whose class mix differs) instead of the surface.
    Returns (rgb (H, W, 3) float in [0, 1] on white, variance (H, W) with NaN where empty,
    extent [x_min, x_max, y_min, y_max] in metres). Large maps use coarser cells so the
    image stays under ``max_pixels`` on a side.
    """
    shown = voxels.label != 0  # class 0: no semantic class (with free space, seen empty)
    if not shown.any():
        return np.ones((1, 1, 3)), np.full((1, 1), np.nan), [0, 1, 0, 1]
    indices, alpha, labels, variances = voxels.indices[shown], voxels.alpha[shown], voxels.label[shown], \
        voxels.variance[shown]
    low, high = indices[:, :2].min(axis=0), indices[:, :2].max(axis=0)
    step = max(1, int(np.ceil((high - low + 1).max() / max_pixels)))
    cell = (indices[:, :2] - low) // step
    width, height = (high - low) // step + 1
    # Sort by total concentration so that, per cell, the last write (the most evident voxel) wins.
    order = np.argsort(alpha.sum(axis=1), kind="stable")
    flat = cell[order, 1] * width + cell[order, 0]
    rgb = np.ones((height * width, 3))
    variance = np.full(height * width, np.nan)
    rgb[flat] = colours[np.clip(labels[order], 0, len(colours) - 1)] / 255.0
    variance[flat] = variances[order]
    extent = [low[0] * resolution, (high[0] + 1) * resolution, low[1] * resolution, (high[1] + 1) * resolution]
    return rgb.reshape(height, width, 3), variance.reshape(height, width), extent


def save_map_picture(voxels: VoxelSet, label_map: LabelMap, resolution: float, path: str | Path,
                     title: str = "") -> None:
    """A bird's-eye PNG: the map in class colours next to its variance."""
    plt = _pyplot()
    rgb, variance, extent = birds_eye_rasters(voxels, label_map.colors, resolution)
    aspect = (extent[3] - extent[2]) / max(extent[1] - extent[0], 1e-6)
    figure, (left, right) = plt.subplots(1, 2, figsize=(15, max(4.0, min(12.0, 7.0 * aspect)) + 1.0))
    left.imshow(rgb, origin="lower", extent=extent, interpolation="nearest")
    left.set_title("expected class (most evident voxel per column)")
    _class_legend(figure, label_map, [c for c in np.unique(voxels.label) if c != 0] if len(voxels) else [])
    from matplotlib.colors import LogNorm

    # Variances span orders of magnitude (well-observed voxels ~1e-4, fringes ~0.1): log colours.
    finite = variance[np.isfinite(variance)]
    low = max(float(finite.min()) if finite.size else 1e-5, 1e-5)
    image = right.imshow(variance, origin="lower", extent=extent, interpolation="nearest", cmap="viridis",
                         norm=LogNorm(vmin=low, vmax=max(low * 10, 0.25)))
    right.set_title("variance of the expected class (log scale)")
    figure.colorbar(image, ax=right, fraction=0.046, pad=0.02)
    for axis in (left, right):
        axis.set_xlabel("x [m]")
        axis.set_ylabel("y [m]")
    if title:
        figure.suptitle(title)
    _save(figure, path)


def save_maps_side_by_side(maps: Sequence[tuple[str, VoxelSet]], label_map: LabelMap, resolution: float,
                           path: str | Path, title: str = "") -> None:
    """Bird's-eye PNG of several maps of one place in class colours, side by side on the same
    axes (``maps``: (caption, voxels)), e.g. a drift drive before and after its correction."""
    plt = _pyplot()
    rasters = [birds_eye_rasters(voxels, label_map.colors, resolution) for _, voxels in maps]
    extents = np.array([extent for _, _, extent in rasters])
    aspect = (extents[:, 3].max() - extents[:, 2].min()) / max(extents[:, 1].max() - extents[:, 0].min(), 1e-6)
    figure, axes = plt.subplots(1, len(maps), figsize=(7.5 * len(maps), max(4.0, min(12.0, 7.0 * aspect)) + 1.0),
                                sharex=True, sharey=True, squeeze=False)
    present = set()
    for axis, (caption, voxels), (rgb, _, extent) in zip(axes[0], maps, rasters):
        axis.imshow(rgb, origin="lower", extent=extent, interpolation="nearest")
        axis.set_title(caption)
        axis.set_xlabel("x [m]")
        axis.set_ylabel("y [m]")
        present.update(int(c) for c in np.unique(voxels.label) if c != 0)
    _class_legend(figure, label_map, sorted(present))
    if title:
        figure.suptitle(title)
    _save(figure, path)


def _class_legend(figure, label_map: LabelMap, classes) -> None:
    """The colours of ``classes`` under the figure (nothing when there are none)."""
    from matplotlib.patches import Patch

    handles = [Patch(color=label_map.colors[c] / 255.0, label=label_map.class_names[c]) for c in classes]
    if handles:
        figure.legend(handles=handles, loc="lower center", ncol=min(len(handles), 10), fontsize=9, frameon=False,
                      bbox_to_anchor=(0.5, -0.02))


def save_reliability_diagram(diagrams: dict, path: str | Path, variance_curve: Sequence[dict] | None = None,
                             title: str = "") -> None:
    """Reliability diagram (accuracy against confidence per bin) and, when given, the variance-filter curve.

    ``diagrams``: {name: (``calibration.Reliability``, ECE)}, e.g. the map and the input;
    ``variance_curve``: [{"threshold", "miou", "kept"}] (threshold None: no filter).
    """
    plt = _pyplot()
    panels = 2 if variance_curve else 1
    figure, axes = plt.subplots(2, panels, figsize=(6.5 * panels, 7.5), squeeze=False,
                                gridspec_kw={"height_ratios": [3, 1]})
    top, bottom = axes[0, 0], axes[1, 0]
    top.plot([0, 1], [0, 1], color="grey", linestyle="--", linewidth=1, label="perfectly calibrated")
    colours = ["tab:blue", "tab:orange", "tab:green", "tab:red"]
    shown = max(len(diagrams), 1)
    for number, (name, (reliability, ece)) in enumerate(diagrams.items()):
        edges = np.asarray(reliability.edges)
        width = np.diff(edges) / shown
        left = edges[:-1] + number * width
        filled = np.asarray(reliability.count) > 0
        colour = colours[number % len(colours)]
        ece_text = "n/a" if ece is None or not np.isfinite(ece) else f"{ece:.3f}"
        top.bar(left[filled], np.asarray(reliability.accuracy)[filled], width=width[filled], align="edge",
                color=colour, alpha=0.6, edgecolor=colour, label=f"{name} (ECE {ece_text})")
        top.plot(np.asarray(reliability.confidence)[filled], np.asarray(reliability.accuracy)[filled], "o",
                 color=colour, markersize=3)
        counts = np.asarray(reliability.count, np.float64)
        bottom.bar(left, counts / max(counts.sum(), 1.0), width=width, align="edge", color=colour, alpha=0.6)
    top.set_xlim(0, 1)
    top.set_ylim(0, 1)
    top.set_ylabel("accuracy of the chosen class")
    top.set_title("reliability (bars: accuracy per confidence bin; dots at mean confidence)")
    top.legend(loc="upper left", fontsize=9)
    bottom.set_xlim(0, 1)
    bottom.set_xlabel("confidence: expected probability of the chosen class")
    bottom.set_ylabel("share of points")
    if variance_curve:
        curve, share = axes[0, 1], axes[1, 1]
        filtered = [entry for entry in variance_curve if entry["threshold"] is not None]
        thresholds = [entry["threshold"] for entry in filtered]
        miou = [np.nan if entry["miou"] is None else entry["miou"] for entry in filtered]
        kept = [np.nan if entry["kept"] is None else entry["kept"] for entry in filtered]
        curve.semilogx(thresholds, miou, "o-", color="tab:blue", label="mIoU of kept points")
        accuracy = [np.nan if entry.get("accuracy") is None else entry["accuracy"] for entry in filtered]
        if not np.isnan(accuracy).all():
            curve.semilogx(thresholds, accuracy, "s-", color="tab:purple", label="accuracy of kept points")
        unfiltered = [entry for entry in variance_curve if entry["threshold"] is None]
        if unfiltered and unfiltered[0]["miou"] is not None:
            curve.axhline(unfiltered[0]["miou"], color="tab:blue", linestyle=":", label="mIoU, no filter")
        curve.axvline(0.01, color="grey", linestyle="--", linewidth=1, label="paper's filter (V > 0.01 dropped)")
        curve.set_ylabel("score of the kept points")
        curve.set_title("variance filter: points whose chosen class has V > threshold dropped")
        curve.legend(loc="best", fontsize=9)
        share.semilogx(thresholds, kept, "o-", color="tab:green")
        share.axvline(0.01, color="grey", linestyle="--", linewidth=1)
        share.set_ylim(0, 1.02)
        share.set_xlabel("variance threshold")
        share.set_ylabel("share kept")
        for axis in (curve, share):
            axis.grid(True, which="both", alpha=0.3)
    if title:
        figure.suptitle(title)
    figure.tight_layout()
    _save(figure, path)


def save_loss_curve(losses: Sequence[float], path: str | Path, title: str = "training loss") -> None:
    """Loss per step and its running mean."""
    plt = _pyplot()
    figure, axis = plt.subplots(figsize=(7, 4))
    steps = np.arange(1, len(losses) + 1)
    axis.plot(steps, losses, alpha=0.35, label="per sample")
    if len(losses) >= 5:
        window = max(5, len(losses) // 20)
        smooth = np.convolve(losses, np.ones(window) / window, mode="valid")
        axis.plot(steps[window - 1:], smooth, label=f"running mean ({window})")
    axis.set_xlabel("step")
    axis.set_ylabel("weighted NLL")
    axis.set_title(title)
    axis.legend()
    _save(figure, path)


def save_kernel_picture(kernel: ConvBKIKernel, class_ids: Sequence[int], class_names: Sequence[str],
                        path: str | Path) -> None:
    """Filters of the given classes in the x-z plane at dy = 0 (like the paper's Fig. 4)."""
    plt = _pyplot()
    filters = kernel.filters().detach().cpu().numpy()[:, 0]
    half = kernel.filter_size // 2
    reach = (half + 0.5) * kernel.resolution
    figure, axes = plt.subplots(1, len(class_ids), figsize=(4 * len(class_ids), 3.8), squeeze=False)
    for axis, class_id in zip(axes[0], class_ids):
        image = axis.imshow(filters[class_id][:, half, :].T, origin="lower", vmin=0, vmax=1, cmap="magma",
                            extent=[-reach, reach, -reach, reach])
        axis.set_title(f"{class_names[class_id]} ({kernel.kind})")
        axis.set_xlabel("dx [m]")
        axis.set_ylabel("dz [m]")
    figure.colorbar(image, ax=list(axes[0]), fraction=0.03)
    _save(figure, path)


def costmap_colours():
    """Costs 0..100: free white, costly yellow to red, lethal black; unknown grey."""
    from matplotlib.colors import LinearSegmentedColormap

    colours = LinearSegmentedColormap.from_list("cost", [(0.0, "white"), (0.01, "#fff3b0"), (0.6, "#e8590c"),
                                                         (0.99, "#c92a2a"), (1.0, "black")])
    colours.set_bad("#9e9e9e")
    return colours


def save_costmap_pictures(grids: dict, road: np.ndarray | None, path: str | Path, title: str = "") -> None:
    """Costmaps side by side (``{name: costmap.CostGrid}``, one extent), north up, with one
    path planned on each (between the two road cells furthest apart that both grids' planner
    reaches)."""
    from convbki_core.measures.costmap_eval import _dijkstra, group_of

    plt = _pyplot()
    figure, axes = plt.subplots(1, len(grids), figsize=(6 * len(grids), 6), squeeze=False)
    path_cells = None
    if road is not None and road.any():
        # The two road cells furthest apart among a few that the first grid's planner connects.
        free = road & np.all([group_of(grid.values) == 0 for grid in grids.values()], axis=0)
        cells = np.flatnonzero(free)
        first = next(iter(grids.values())).values
        rng = np.random.default_rng(0)
        best = 0.0
        for _ in range(30 if len(cells) >= 2 else 0):
            a, b = rng.choice(cells, 2, replace=False)
            distance = np.hypot(*np.subtract(divmod(a, free.shape[1]), divmod(b, free.shape[1])))
            if distance > best and len(_dijkstra(first, int(a), int(b), 25.0)[1]):
                best, path_cells = distance, (a, b)
    for axis, (name, grid) in zip(axes[0], grids.items()):
        values = np.ma.masked_less(grid.values.astype(np.float32), 0)
        height, width = grid.values.shape
        low = grid.origin_metres
        extent = (low[0], low[0] + width * grid.resolution, low[1], low[1] + height * grid.resolution)
        axis.imshow(values, cmap=costmap_colours(), vmin=0, vmax=100, origin="lower", interpolation="nearest",
                    extent=extent)
        if path_cells is not None:
            _, planned = _dijkstra(grid.values, int(path_cells[0]), int(path_cells[1]), 25.0)
            if len(planned):
                ys, xs = np.divmod(planned, width)
                axis.plot(low[0] + (xs + 0.5) * grid.resolution, low[1] + (ys + 0.5) * grid.resolution, "c-",
                          linewidth=1.5)
        axis.set_title(name)
        axis.set_xlabel("x (m)")
        axis.set_ylabel("y (m)")
        axis.set_aspect("equal")
    if title:
        figure.suptitle(title)
    _save(figure, path)
