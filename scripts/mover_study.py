"""Moving objects across a family of drives: the product's defaults against plain ConvBKI.

    .venv/bin/python scripts/mover_study.py --out out/movers_study \
        --drive 60:10:901 --drive 60:20:902:moving --drive 300:16:904 [--traffic varied]

Each ``--drive FRAMES:MOVERS:SEED[:moving]`` is made with ``synth`` (its own streets, speeds
and mix of behaviours; ``moving``: the predictions carry moving raw ids, as a multi-scan
network's do) unless OUT/dSEED already holds it, then mapped twice under the paper's
protocol with the same kernel: plain ConvBKI (no free space, moving labels mapped as their
static classes), free space and clamping alone, and the shipped defaults (free space,
clamping, the movers' rules, moving labels used). Prints one markdown table row per drive
(trail voxels and their share of plain's, mIoU, static coverage, the median update time)
and one per movable class (IoU of the input and of each map), and writes
OUT/mover_study.json.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from convbki_core.config import DEFAULTS, PAPER_KERNEL
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.io.atomic import atomic_write_bytes
from convbki_core.measures.metrics import ConfusionMatrix
from convbki_core.paths import kernel_path
from convbki_core.tools.evaluate_run import evaluate_kernel
from convbki_core.tools.synth import main as synth_main


def make_drive(out: Path, frames: int, movers: int, seed: int, moving: bool, traffic: str) -> Path:
    root = out / f"d{seed}"
    if not (root / "sequences" / "00" / "poses.txt").exists():
        argv = ["--out", str(root), "--sequence", "00", "--frames", str(frames), "--seed", str(seed),
                "--movers", str(movers), "--traffic", traffic, "--quiet", "--force"]
        if moving:
            argv.append("--moving-labels")
        if synth_main(argv) != 0:
            raise SystemExit(f"synth failed for seed {seed}")
    return root


def study(root: Path) -> dict:
    dataset = SemanticKittiSequence(root, "00")
    positions = range(len(dataset))
    kernel = kernel_path(PAPER_KERNEL)
    names = dataset.label_map.class_names
    movable = dataset.label_map.movable_classes
    input_scores = ConfusionMatrix(dataset.label_map.num_classes, dataset.label_map.ignore_classes)
    # Plain ConvBKI: every point is mapped as its static class, nothing is ever emptied.
    cpu = DEFAULTS.replace(device="cpu")
    plain = evaluate_kernel(dataset, positions, kernel, cpu.replace(free_space=False), input_scores, None,
                            show_progress=False, moving_labels=False)
    # Free space and clamping alone (the defaults of the version before the movers' rules).
    free = evaluate_kernel(dataset, positions, kernel, cpu.replace(forget_movers=False), None, None,
                           show_progress=False, moving_labels=False)
    product = evaluate_kernel(dataset, positions, kernel, cpu, None, None, show_progress=False)
    runs = {"plain": plain, "free": free, "product": product}
    iou_input = input_scores.iou()
    ious = {name: run.map_scores.iou() for name, run in runs.items()}
    return {"frames": len(dataset), "moving_labels": product.moving_labels_used,
            "trails": {name: run.trail_voxels for name, run in runs.items()},
            "miou": {"input": input_scores.miou(), **{name: run.map_scores.miou() for name, run in runs.items()}},
            "coverage": {name: run.static_coverage for name, run in runs.items()},
            "update_ms": {name: float(sorted(run.update_ms)[len(run.update_ms) // 2]) for name, run in runs.items()},
            "movable": {names[c]: {"input": float(iou_input[c]), **{name: float(iou[c]) for name, iou in ious.items()}}
                        for c in movable if input_scores.present[c]}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/movers_study")
    parser.add_argument("--drive", action="append", required=True, help="FRAMES:MOVERS:SEED[:moving]")
    parser.add_argument("--traffic", default="varied", choices=("classic", "varied"))
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    for spec in args.drive:
        parts = spec.split(":")
        frames, movers, seed = (int(p) for p in parts[:3])
        moving = len(parts) > 3 and parts[3] == "moving"
        root = make_drive(out, frames, movers, seed, moving, args.traffic)
        results[spec] = study(root)
        r = results[spec]
        trails, miou, coverage, times = r["trails"], r["miou"], r["coverage"], r["update_ms"]

        def share(name: str, trails=trails) -> str:
            return f"{trails[name]:,} ({100 * trails[name] / max(trails['plain'], 1):.1f} %)"

        worst = min((m["product"] - m["input"] for m in r["movable"].values()), default=0.0)
        print(f"| {spec} | {trails['plain']:,} | {share('free')} | {share('product')} "
              f"| {miou['input']:.3f} | {miou['plain']:.3f} | {miou['free']:.3f} | {miou['product']:.3f} "
              f"| {100 * coverage['plain']:.1f} | {100 * coverage['free']:.1f} | {100 * coverage['product']:.1f} "
              f"| {worst:+.3f} | {times['plain']:.1f} / {times['free']:.1f} / {times['product']:.1f} |", flush=True)
        for name, m in r["movable"].items():
            print(f"|   {name} | input {m['input']:.3f} | plain {m['plain']:.3f} | free {m['free']:.3f} "
                  f"| product {m['product']:.3f} | {m['product'] - m['input']:+.3f} |", flush=True)
        atomic_write_bytes(out / "mover_study.json", json.dumps(results, indent=2).encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
