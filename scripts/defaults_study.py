"""The product's defaults against plain ConvBKI on a set of drives and real sequences: what the
movers' rules keep of parked and standing objects, what they remove of movers, and what the
car's costmap makes of the road.

    .venv/bin/python scripts/defaults_study.py --out out/defaults_study \
        --drive 80:0:11001 --drive 80:12:11003 --real out/real_noisy:05 \
        [--variant 'NAME:setting=value;...'] [--costmap] [--frames A:B]

``--drive FRAMES:MOVERS:SEED[:moving]`` is a synthetic drive (made with ``synth`` unless
OUT/dSEED holds it; ``moving``: its input carries moving raw ids); ``--real ROOT:SS`` a
sequence in SemanticKITTI layout with an input segmentation (e.g. written by ``label_noise``).
Each is mapped under the paper's protocol with the same kernel by plain ConvBKI (no free
space), the shipped defaults and every ``--variant`` (the defaults with ``MapperConfig``
settings changed by their flat names, e.g. ``no_rules:forget_movers=false``). Prints, per
drive, one markdown row per run (mIoU, trail voxels and their share of plain's, update time)
and the movable classes' IoU over all points, over the points the ground truth does not mark
as moving (parked, standing) and over those it does; with ``--costmap``, the car profile's
costmap scores of the input's grid, plain's and each run's. Writes OUT/defaults_study.json.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from convbki_core.config import DEFAULTS, PAPER_KERNEL
from convbki_core.datasets import parse_frames
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.io.atomic import atomic_write_bytes
from convbki_core.io.kernel_file import load_kernel_file
from convbki_core.measures.metrics import ConfusionMatrix
from convbki_core.paths import kernel_path
from convbki_core.tools.evaluate_run import evaluate_kernel
from convbki_core.tools.synth import main as synth_main


def make_drive(out: Path, frames: int, movers: int, seed: int, moving: bool) -> Path:
    root = out / f"d{seed}"
    if not (root / "sequences" / "00" / "poses.txt").exists():
        argv = ["--out", str(root), "--sequence", "00", "--frames", str(frames), "--seed", str(seed),
                "--movers", str(movers), "--quiet", "--force"]
        if moving:
            argv.append("--moving-labels")
        if synth_main(argv) != 0:
            raise SystemExit(f"synth failed for seed {seed}")
    return root


def parse_value(text: str):
    if text.startswith("["):
        return json.loads(text)
    lowered = text.lower()
    if lowered in ("true", "false"):
        return lowered == "true"
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def parse_variant(text: str) -> tuple[str, dict]:
    name, _, settings = text.partition(":")
    changes = {}
    for item in filter(None, settings.split(";")):
        key, _, value = item.partition("=")
        changes[key] = parse_value(value)
    return name, changes


def costmap_scores(mapper, truth_voxels, input_voxels, profile, label_map) -> dict:
    from convbki_core.measures.costmap_eval import grids_for, planning_check, road_cells, score_grid

    indices, alpha = mapper.items()
    grids = grids_for(indices, alpha, truth_voxels, mapper.resolution, mapper.prior, profile, input_voxels)
    road = road_cells(truth_voxels, grids["truth"], label_map.class_names.index("road"))
    scores = {}
    for name in [name for name in ("map", "input") if name in grids]:
        score = score_grid(grids[name].values, grids["truth"].values)
        check = planning_check(grids[name].values, grids["truth"].values, road).summary()
        scores[name] = {"precision": score.precision, "recall": score.recall, "unknown_share": score.unknown_share,
                        "planning": check}
    return scores


def study(root: Path, sequence: str, frames: str | None, variants: dict[str, dict], with_costmap: bool) -> dict:
    dataset = SemanticKittiSequence(root, sequence)
    positions = parse_frames(frames, len(dataset))
    kernel = kernel_path(PAPER_KERNEL)
    label_map = dataset.label_map
    names = label_map.class_names
    input_scores = ConfusionMatrix(label_map.num_classes, label_map.ignore_classes)
    cpu = DEFAULTS.replace(device="cpu")
    profile = None
    if with_costmap:
        from convbki_core.costmap.profile import load_profile
        from convbki_core.paths import traversability_profile

        profile = load_profile(traversability_profile("car"), names)
    runs, costmaps = {}, {}
    configs = {"plain": cpu.replace(free_space=False), "defaults": cpu,
               **{name: cpu.replace(**changes) for name, changes in variants.items()}}
    for number, (name, config) in enumerate(configs.items()):
        truth_voxels = input_voxels = None
        if profile is not None:
            from convbki_core.measures.costmap_eval import GroundTruthVoxels

            truth_voxels = GroundTruthVoxels(label_map.num_classes, load_kernel_file(kernel).resolution)
            input_voxels = GroundTruthVoxels(label_map.num_classes, truth_voxels.resolution) if number == 0 else None
        started = time.perf_counter()
        result = evaluate_kernel(dataset, positions, kernel, config, input_scores if number == 0 else None, None,
                                 show_progress=False, moving_labels=name != "plain", truth_voxels=truth_voxels,
                                 input_voxels=input_voxels)
        runs[name] = result
        if profile is not None:
            scores = costmap_scores(result.mapper, truth_voxels, input_voxels, profile, label_map)
            if "input" in scores:
                costmaps["input"] = scores.pop("input")
            costmaps[name] = scores["map"]
        print(f"  {root.name}/{sequence} {name}: {time.perf_counter() - started:.0f} s", file=sys.stderr, flush=True)
    plain_trails = runs["plain"].trail_voxels
    summary = {"drive": f"{root}:{sequence}", "frames": len(positions), "input_miou": input_scores.miou(),
               "runs": {}, "costmap": costmaps}
    present = np.flatnonzero(input_scores.present)
    for name, result in runs.items():
        entry = {"miou": result.map_scores.miou(), "trail_voxels": result.trail_voxels,
                 "trail_share": (result.trail_voxels / plain_trails if plain_trails and result.trail_voxels is not None
                                 else None),
                 "update_ms_median": float(np.median(result.update_ms)),
                 "iou": {names[c]: float(result.map_scores.iou()[c]) for c in present},
                 "static_iou": {}, "moving_iou": {}}
        for c in label_map.movable_classes:
            if result.static_map_scores is not None and result.static_map_scores.present[c]:
                entry["static_iou"][names[c]] = float(result.static_map_scores.iou()[c])
            if result.moving_map_scores is not None and result.moving_map_scores.present[c]:
                entry["moving_iou"][names[c]] = float(result.moving_map_scores.iou()[c])
        summary["runs"][name] = entry
    first = runs["plain"]
    summary["input"] = {"iou": {names[c]: float(input_scores.iou()[c]) for c in present},
                        "static_iou": {names[c]: float(first.static_input_scores.iou()[c])
                                       for c in label_map.movable_classes if first.static_input_scores.present[c]},
                        "moving_iou": {names[c]: float(first.moving_input_scores.iou()[c])
                                       for c in label_map.movable_classes
                                       if first.moving_input_scores is not None
                                       and first.moving_input_scores.present[c]}}
    summary["movable_classes"] = [names[c] for c in label_map.movable_classes if input_scores.present[c]]
    return summary


def _pct(value) -> str:
    return "-" if value is None else f"{100 * value:.1f}"


def print_tables(summary: dict) -> None:
    print(f"\n### {summary['drive']} ({summary['frames']} scans), input mIoU {summary['input_miou']:.3f}\n")
    print("| run | mIoU | trail voxels (share of plain's) | update ms |")
    print("|---|---|---|---|")
    for name, run in summary["runs"].items():
        trails = "-" if run["trail_voxels"] is None else f"{run['trail_voxels']} ({_pct(run['trail_share'])} %)"
        print(f"| {name} | {run['miou']:.3f} | {trails} | {run['update_ms_median']:.1f} |")
    movable = summary["movable_classes"]
    if movable:
        print("\nmovable classes, IoU % all / not moving / moving:\n")
        print("| class | input | " + " | ".join(summary["runs"]) + " |")
        print("|---|---|" + "---|" * len(summary["runs"]))
        for cls in movable:
            cells = [f"{_pct(summary['input']['iou'].get(cls))} / {_pct(summary['input']['static_iou'].get(cls))} / "
                     f"{_pct(summary['input']['moving_iou'].get(cls))}"]
            for run in summary["runs"].values():
                cells.append(f"{_pct(run['iou'].get(cls))} / {_pct(run['static_iou'].get(cls))} / "
                             f"{_pct(run['moving_iou'].get(cls))}")
            print(f"| {cls} | " + " | ".join(cells) + " |")
    if summary["costmap"]:
        print("\ncar costmap, %: free P / R, lethal P / R, unknown, paths within 5 % of the truth's, crossing "
              "truth-lethal:\n")
        print("| grid | free P / R | lethal P / R | unknown | within 5 % | crossing |")
        print("|---|---|---|---|---|---|")
        for name, scores in summary["costmap"].items():
            planning = scores["planning"]
            within = planning.get("within_5_percent")
            print(f"| {name} | {_pct(scores['precision']['free'])} / {_pct(scores['recall']['free'])} | "
                  f"{_pct(scores['precision']['lethal'])} / {_pct(scores['recall']['lethal'])} | "
                  f"{_pct(scores['unknown_share'])} | {_pct(within)} | {planning.get('crossing_truth_lethal')} |")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True)
    p.add_argument("--drive", action="append", default=[], metavar="FRAMES:MOVERS:SEED[:moving]")
    p.add_argument("--real", action="append", default=[], metavar="ROOT:SS")
    p.add_argument("--variant", action="append", default=[], metavar="NAME:setting=value;...")
    p.add_argument("--costmap", action="store_true", help="also score the car profile's costmap")
    p.add_argument("--frames", default=None, metavar="A:B")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    variants = dict(parse_variant(text) for text in args.variant)
    datasets = []
    for text in args.drive:
        parts = text.split(":")
        datasets.append((make_drive(out, int(parts[0]), int(parts[1]), int(parts[2]), parts[3:] == ["moving"]), "00"))
    for text in args.real:
        root, _, sequence = text.rpartition(":")
        datasets.append((Path(root), sequence))
    results = []
    for root, sequence in datasets:
        summary = study(root, sequence, args.frames, variants, args.costmap)
        print_tables(summary)
        results.append(summary)
    atomic_write_bytes(out / "defaults_study.json", (json.dumps(results, indent=1) + "\n").encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
