"""``map_tool``: inspect, merge and export ConvBKI map files (the ``mapfile`` format).

* ``info``: what a map holds (voxels, bounds, classes, settings, sizes);
* ``merge``: the union of maps built in one frame. The ConvBKI update is a sum of
  kernel-weighted evidence on top of the prior, so a voxel present in k maps has the
  concentration sum_i alpha_i - (k - 1) * prior: without free space the map one mapper
  would have built from all their scans (up to float32 rounding). With free space it is the
  sum of the maps' evidence, not quite one mapper's: a map's rays emptied only the voxels
  that map held, and clamping (which keeps the prior) is not a sum;
* ``export-ply``: the voxel centres in class colours, for CloudCompare, Open3D or MeshLab;
* ``costmap``: the map's traversability grid for a robot profile (``convbki_core.costmap.columns``),
  as the node's ``~/get_costmap`` gives it, to a ``.npz`` or a ``.png``.

This module is the command line; ``map_info`` reads what a map holds, ``map_merge`` sums maps.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from convbki_core.tools.cli import UserError, output_folder, positive, run
from convbki_core.tools.map_info import class_names_for, format_info, map_info
from convbki_core.tools.map_merge import check_same, merge_arrays

if TYPE_CHECKING:
    from convbki_core.map_contents import VoxelSet

PROG = "map_tool"


class _Parser(argparse.ArgumentParser):
    """argparse whose errors (subcommands' included) are one line and exit 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{PROG}: error: {message} (see {self.prog} --help)\n")


def _steps(total: int, quiet: bool, description: str):
    """A step progress bar on stderr; off with --quiet or when stderr is not a terminal (logs)."""
    from tqdm import tqdm

    return tqdm(total=total, desc=description, unit="step", file=sys.stderr, leave=False,
                disable=True if quiet else None, dynamic_ncols=True)


def _check_output(path: str, force: bool) -> Path:
    """Refuse, before any work, an output that cannot be written or would replace a file unasked."""
    out = Path(path)
    output_folder(out)
    if out.is_dir():
        raise UserError(f"{out}: is a folder; --out names a file")
    if out.exists() and not force:
        raise UserError(f"{out}: already exists (use --force to replace it)")
    return out


# -- merge --------------------------------------------------------------------------------
def _merge(args: argparse.Namespace) -> int:
    from convbki_core.io.map_file import MapSnapshot, read_map

    names = [args.first, *args.rest]
    out = _check_output(args.out, args.force)
    seen: dict[Path, str] = {}
    for name in names:
        if Path(name).resolve() in seen:
            raise UserError(f"{name}: given twice (as {seen[Path(name).resolve()]}); each map counts once")
        seen[Path(name).resolve()] = name
    maps = []
    with _steps(len(names) + 2, args.quiet, "merge") as bar:
        for name in names:
            bar.set_description(f"reading {Path(name).name}")
            metadata, indices, alpha = read_map(name)
            prior = metadata.get("prior")
            if isinstance(prior, bool) or not isinstance(prior, (int, float)) or not prior > 0:
                raise UserError(f"{name}: metadata has no positive prior ({prior!r}), so the merge cannot count "
                                "it once")
            if maps:
                check_same((names[0], maps[0][0]), (name, metadata))
            # Every class of every voxel starts at the prior and only grows: anything below was built otherwise.
            if len(alpha) and alpha.min() < prior * (1 - 1e-6):
                raise UserError(f"{name}: holds concentrations below its prior {prior}, so it was not built "
                                "with that prior (or by a version whose clamping scaled the prior too) and the "
                                "merge would not be exact")
            maps.append((metadata, indices, alpha))
            bar.update()
        bar.set_description("merging")
        prior = float(maps[0][0]["prior"])
        indices, alpha, shared = merge_arrays([(m[1], m[2]) for m in maps], prior)
        bar.update()
        metadata = dict(maps[0][0], num_voxels=len(indices), merged_from=names)
        scans = [m[0].get("scans_integrated") for m in maps]
        if all(value is not None for value in scans):
            metadata["scans_integrated"] = int(sum(scans))
        else:
            metadata.pop("scans_integrated", None)  # unknown for some input: a partial sum would mislead
        bar.set_description(f"writing {out.name}")
        MapSnapshot(metadata, indices, alpha).write(out)
        bar.update()
    sizes = " + ".join(str(len(m[1])) for m in maps)
    print(f"merged {len(maps)} maps ({sizes} voxels) into {len(indices)} voxels, {shared} in more than one: {out}")
    return 0


# -- export-ply ---------------------------------------------------------------------------
def voxel_set(indices: np.ndarray, alpha: np.ndarray, resolution: float) -> VoxelSet:
    """A ``map_contents.VoxelSet`` (centres in m, expected class, variance) of map-file arrays."""
    from convbki_core.geometry.grid import voxel_centres
    from convbki_core.inference.statistics import dirichlet_statistics
    from convbki_core.map_contents import VoxelSet

    stats = dirichlet_statistics(alpha)
    return VoxelSet(indices, voxel_centres(indices, resolution).astype(np.float32), alpha, stats.label,
                    stats.confidence, stats.variance)


def _export_ply(args: argparse.Namespace) -> int:
    from convbki_core.io.map_file import read_map
    from convbki_core.io.ply import write_voxels_ply

    out = _check_output(args.out, args.force)
    with _steps(3, args.quiet, "export-ply") as bar:
        bar.set_description(f"reading {Path(args.map).name}")
        metadata, indices, alpha = read_map(args.map)
        bar.update()
        bar.set_description("statistics")
        voxels = voxel_set(indices, alpha, float(metadata["resolution"]))
        bar.update()
        bar.set_description(f"writing {out.name}")
        written = write_voxels_ply(voxels, out, max_variance=args.max_variance)
        bar.update()
    kept = f" (of {len(voxels)}; variance <= {args.max_variance:g})" if args.max_variance else ""
    print(f"wrote {written} voxels{kept} to {out}")
    return 0


def _costmap(args: argparse.Namespace) -> int:
    from convbki_core.costmap.columns import column_costs
    from convbki_core.costmap.grid import rasterise
    from convbki_core.costmap.profile import ProfileError, load_profile
    from convbki_core.io.atomic import atomic_write_with
    from convbki_core.io.map_file import read_map
    from convbki_core.paths import traversability_profile

    out = _check_output(args.out, args.force)
    if out.suffix not in (".npz", ".png"):
        raise UserError(f"{out}: --out must end in .npz or .png")
    with _steps(3, args.quiet, "costmap") as bar:
        bar.set_description(f"reading {Path(args.map).name}")
        metadata, indices, alpha = read_map(args.map)
        names = class_names_for(metadata)
        if names is None:
            raise UserError(f"{args.map}: no class names for its {metadata['num_classes']} classes")
        try:
            profile = load_profile(traversability_profile(args.profile), tuple(names))
        except ProfileError as error:
            raise UserError(str(error)) from None
        bar.update()
        bar.set_description("costs")
        resolution = float(metadata["resolution"])
        grid = rasterise(column_costs(indices, alpha, resolution, profile, float(metadata["prior"])), resolution)
        bar.update()
        bar.set_description(f"writing {out.name}")
        if out.suffix == ".png":
            from convbki_core.tools.plots import save_costmap_pictures

            save_costmap_pictures({f"costmap ({profile.name})": grid}, None, out)
        else:
            def write(handle) -> None:
                np.savez_compressed(handle, values=grid.values, origin=grid.origin_metres,
                                    resolution=np.float64(resolution), profile=np.str_(profile.name),
                                    frame_id=np.str_(metadata.get("frame_id") or ""))
            atomic_write_with(out, write)
        bar.update()
    values = grid.values
    known = values >= 0
    print(f"wrote a {values.shape[1]} x {values.shape[0]} costmap ({profile.name}, {resolution:g} m cells) to "
          f"{out}: {int(known.sum())} observed cells, {int((values == 0).sum())} free, "
          f"{int((values >= 100).sum())} lethal")
    return 0


# -- correct ------------------------------------------------------------------------------
def _pending_poses(path, log, scans) -> dict:
    """The logged scans' poses by the SLAM's Path a node had not yet applied when it saved the map."""
    from convbki_core.correction.replay import keyframe_corrections

    if log.pending is None:
        raise UserError(f"{path}: holds no SLAM correction left to apply (the node applied every Path it took); "
                        "give --poses POSES.txt")
    stamps, poses = log.pending
    return keyframe_corrections(scans, stamps, poses)


def _poses_file_poses(args: argparse.Namespace, log, scans) -> dict:
    """The logged scans' poses by a poses file (one line per logged scan, ``poses.txt``'s format)."""
    from convbki_core.datasets import DatasetError
    from convbki_core.datasets.semantic_kitti import read_calibration, read_poses

    calibration = log.calibration
    try:
        if args.calib:
            calibration = read_calibration(Path(args.calib))
        if calibration is None:
            raise UserError(f"{args.map}: its log keeps no calibration (the scans came from a node, in the sensor's "
                            "frame): give --calib CALIB.txt, or an identity one for poses of the sensor")
        poses = read_poses(Path(args.poses), calibration)
    except DatasetError as error:
        raise UserError(str(error)) from None
    if len(poses) != len(scans):
        raise UserError(f"{args.poses}: {len(poses)} poses for the {len(scans)} logged scans (scans "
                        f"{scans[0][0]}..{scans[-1][0]} of the map); one pose per logged scan, in order"
                        + (f"; the {log.frozen} scans before are frozen ({log.frozen_why})" if log.frozen else ""))
    return {index: pose for (index, _), pose in zip(scans, poses)}


def _correct(args: argparse.Namespace) -> int:
    """Map the logged scans of a map file again at the poses of a poses file, or of the SLAM's
    Path the node had not yet applied when it saved the map."""
    from convbki_core.config import MapperConfig
    from convbki_core.io.kernel_file import kernel_config_from_dict
    from convbki_core.io.map_file import read_map
    from convbki_core.mapper import ConvBKIMapper

    out = _check_output(args.out, args.force)
    metadata, indices, alpha = read_map(args.map, with_scan_log=True)
    log = metadata["scan_log"]
    if log is None:
        raise UserError(f"{args.map}: holds no scan log (saved with scan_log off, or by a version before "
                        "logs), so none of its scans can move")
    scans = log.scans()
    if not scans:
        raise UserError(f"{args.map}: its scan log is empty; its {log.frozen} scans are frozen into the map "
                        f"({log.frozen_why or 'they cannot move'})")
    wanted = _pending_poses(args.map, log, scans) if args.poses is None else _poses_file_poses(args, log, scans)
    try:
        config = MapperConfig.from_mapping_record(metadata.get("mapping"))
        kernel = kernel_config_from_dict(metadata.get("kernel"))
    except (ValueError, TypeError, KeyError) as error:
        raise UserError(f"{args.map}: does not say how its scans were mapped ({error})") from None
    # The log as the file holds it, unbounded; the device where no GPU is asked for.
    config = config.replace(device="cpu", scan_log_scans=0, scan_log_megabytes=0.0)
    mapper = ConvBKIMapper(config, kernel)
    if any(scan.data.place is not None for _, scan in scans):
        # A log in a folder: FIXED names MAP's scans there, and its own new bases go beside it.
        mapper.use_log_folder(f"{out}.scan_log")
    mapper.replace_with(metadata, indices, alpha)
    with _steps(1, args.quiet, "mapping the moved scans again") as bar:
        corrected, result = mapper.corrected(wanted, tolerance=args.tolerance)
        bar.update()
    if corrected.scan_log is not None:
        corrected.scan_log.pending = None  # applied (or overruled by --poses)
    corrected.save(out)
    if corrected.scan_log is not None and corrected.scan_log.folder is not None:
        corrected.scan_log.folder.close(remove_folder=True)  # (removed only when FIXED names none of it)
    print(f"corrected {args.map}: {result.scans} of {len(scans)} logged scans moved (largest move "
          f"{result.largest_move:.2f} m; {result.skipped} moved less than {args.tolerance:g} m, left alone), "
          f"{result.replayed} mapped again in {result.seconds:.2f} s: {out} ({len(corrected)} voxels)")
    return 0


def _info(args: argparse.Namespace) -> int:
    import json

    with _steps(1, args.quiet, f"reading {Path(args.map).name}") as bar:
        info = map_info(args.map)
        bar.update()
    print(json.dumps(info) if args.json else format_info(info))
    return 0


def build_parser() -> argparse.ArgumentParser:
    """Command-line parser: one subcommand per task."""
    p = _Parser(
        prog=PROG, formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Inspect, merge and export ConvBKI map files (written by the mapper node's save service, "
        "its map_file autosave, or evaluate --save-map).",
        epilog="commands:\n"
        "  map_tool info MAP [--json]\n"
        "  map_tool merge MAP MAP [MAP ...] --out MAP [--force]\n"
        "  map_tool export-ply MAP --out PLY [--max-variance V] [--force]\n"
        "  map_tool costmap MAP --out GRID.npz|GRID.png [--profile car|small_robot|FILE] [--force]\n"
        "  map_tool correct MAP [--poses POSES.txt] --out FIXED [--calib CALIB.txt] [--tolerance M] [--force]\n"
        "  --json: one JSON object; --out: the file to write (atomically); --force: replace it if it exists;\n"
        "  --max-variance: only voxels whose expected class has at most this variance; --quiet: no progress bar.\n"
        "`map_tool COMMAND --help` explains each command.")
    commands = p.add_subparsers(dest="command", metavar="COMMAND", required=True)
    info = commands.add_parser("info", help="print what a map holds", description="Print a map's voxel count, "
                               "bounds (voxel indices and metres, in its frame), resolution, frame_id, prior, kernel, "
                               "scans integrated, voxels per expected class, file size and memory per voxel.")
    info.add_argument("map", metavar="MAP", help="map file to read")
    info.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    merge = commands.add_parser("merge", help="merge maps built in one frame (their evidence summed)",
                                description="Merge maps built in one frame with the same resolution, classes and "
                                "prior (e.g. two halves of a drive): a voxel in k maps gets the sum of their "
                                "concentrations minus (k - 1) x prior. Without free space that is the map one mapper "
                                "would have built from all their scans; with free space, the sum of their evidence "
                                "(a map's rays emptied only the voxels it held).")
    merge.add_argument("first", metavar="MAP", help="first map; the output keeps its metadata")
    merge.add_argument("rest", metavar="MAP", nargs="+", help="more maps to add")
    merge.add_argument("--out", required=True, metavar="MAP", help="merged map file to write (atomically)")
    merge.add_argument("--force", action="store_true", help="replace --out if it exists (it may be an input)")
    export = commands.add_parser("export-ply", help="write a map as a PLY point cloud in class colours",
                                 description="Write one vertex per voxel centre (m) with its class colour, class "
                                 "id and variance of its expected class, as binary PLY.")
    export.add_argument("map", metavar="MAP", help="map file to read")
    export.add_argument("--out", required=True, metavar="PLY", help="PLY file to write (atomically)")
    export.add_argument("--max-variance", type=positive(float, "--max-variance"), default=None, metavar="V",
                        help="only voxels whose expected class has at most this variance (default: all)")
    export.add_argument("--force", action="store_true", help="replace --out if it exists")
    costmap = commands.add_parser("costmap", help="write the map's traversability costmap for a robot profile",
                                  description="The cost of every observed column (0 free .. 100 lethal, -1 "
                                  "unknown) as the mapper's semantic_map/costmap has it: the expected class cost "
                                  "under each voxel's posterior plus a risk margin, from the ground up to the "
                                  "robot's height. .npz: values (rows = y), origin (m), resolution, profile, "
                                  "frame_id; .png: a picture.")
    costmap.add_argument("map", metavar="MAP", help="map file to read")
    costmap.add_argument("--out", required=True, metavar="GRID", help=".npz or .png file to write (atomically)")
    costmap.add_argument("--profile", default="car", metavar="PROFILE",
                         help="traversability profile: car or small_robot (shipped), or a YAML file (default: car)")
    costmap.add_argument("--force", action="store_true", help="replace --out if it exists")
    correct = commands.add_parser("correct", help="move the map's logged scans to corrected poses (a SLAM's)",
                                  description="Map the scans a map file's scan log keeps again, each at its pose "
                                  "of POSES (one pose per logged scan, in order: poses.txt's format, read with the "
                                  "calibration the scans were read with, kept in the log, or --calib): the map "
                                  "built from scratch with those poses, for every rule of the mapper. `map_tool info` "
                                  "says which scans the log keeps.")
    correct.add_argument("map", metavar="MAP", help="map file with a scan log (node map_file, evaluate --save-map)")
    correct.add_argument("--poses", default=None, metavar="POSES",
                         help="corrected poses, one per logged scan (default: the SLAM's Path the node had not "
                         "yet applied when it saved MAP, kept in its log)")
    correct.add_argument("--out", required=True, metavar="FIXED", help="corrected map file to write (atomically)")
    correct.add_argument("--calib", default=None, metavar="CALIB",
                         help="calib.txt whose Tr reads POSES (default: the one kept in the log)")
    correct.add_argument("--tolerance", type=float, default=0.0, metavar="M",
                         help="leave alone scans whose points within the local window move less than this "
                         "(m; default: 0, every scan whose pose differs)")
    correct.add_argument("--force", action="store_true", help="replace --out if it exists (it may be MAP)")
    for command in (info, merge, export, costmap, correct):
        command.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    commands = {"info": _info, "merge": _merge, "export-ply": _export_ply, "costmap": _costmap,
                "correct": _correct}
    return run(PROG, lambda args: commands[args.command](args), build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
