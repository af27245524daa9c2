"""The figures of docs/slam.md: drift drives corrected by their SLAM's keyframes.

For each drive (made with ``synth --drift`` when its folder is missing), the three maps of
``correction_eval.drift_study`` with the paper's set-up and with the shipped defaults:
without correction, corrected, from scratch; mIoU, double surface and labels equal to the
from-scratch map; the concentrations' largest relative difference from the from-scratch map;
the correction's cost against integrating the same scans. Prints a markdown table and writes
``OUT/study.json`` and the before/after picture of the first drive.

    .venv/bin/python scripts/correction_study.py --out out/s46fresh --seeds 51 52 53
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from convbki_core.config import MapperConfig
from convbki_core.datasets.drift import read_loop_closure
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.mapper import ConvBKIMapper
from convbki_core.measures.correction_eval import drift_study
from convbki_core.tools import synth
from convbki_core.tools.plots import save_maps_side_by_side

# (heading bias in degrees per 100 m, scale error) per drive, in the order of --seeds.
DRIFTS = ((8.0, 0.01), (5.0, -0.02), (12.0, 0.005), (3.0, 0.03))


def make_drive(folder: Path, seed: int, drift: tuple[float, float], frames: int, closure: int) -> None:
    if (folder / "sequences" / "00" / "loop_closure.yaml").exists():
        return
    assert synth.main(["--out", str(folder), "--sequence", "00", "--frames", str(frames), "--seed", str(seed),
                       "--movers", "12", "--drift", str(drift[0]), "--drift-scale", str(drift[1]),
                       "--loop-closure", str(closure), "--quiet"]) == 0


def largest_relative_difference(a, b) -> float:
    """max |a - b| / b over the voxels of both maps (they must hold the same voxels)."""
    ia, aa = a.items()
    ib, ab = b.items()
    oa, ob = np.lexsort(ia.T[::-1]), np.lexsort(ib.T[::-1])
    if len(ia) != len(ib) or not np.array_equal(ia[oa], ib[ob]):
        return float("inf")
    return float(np.max(np.abs(aa[oa] - ab[ob]) / ab[ob]))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--seeds", type=int, nargs="+", default=[51, 52, 53])
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--closure", type=int, default=120)
    args = parser.parse_args()
    out = Path(args.out)
    rows, results = [], {}
    setups = {"paper": MapperConfig.paper(device="cpu"), "defaults": MapperConfig().replace(device="cpu")}
    for number, seed in enumerate(args.seeds):
        drift = DRIFTS[number % len(DRIFTS)]
        folder = out / f"drive{seed}"
        make_drive(folder, seed, drift, args.frames, args.closure)
        dataset = SemanticKittiSequence(folder, "00")
        closure = read_loop_closure(dataset)
        for name, config in setups.items():
            study = drift_study(dataset, range(len(dataset)), closure, lambda config=config: ConvBKIMapper(config))
            report = study.report()
            report["max_relative_difference_corrected"] = largest_relative_difference(study.maps[1].mapper,
                                                                                      study.maps[2].mapper)
            results[f"{seed} {name}"] = report
            for entry in study.maps:
                rows.append(f"| {seed} ({drift[0]:g} deg/100 m, {100 * drift[1]:+g} %) | {name} | {entry.name} | "
                            f"{entry.miou:.4f} | {entry.double_surface:.4f} | {100 * entry.labels_equal:.2f} |")
            c = report["correction"]
            rows.append(f"| | {name} | correction | {c['scans_moved']} scans moved, largest {c['largest_move_m']:.2f} m"
                        f" | {c['ms_per_moved_scan']:.1f} ms a scan vs {c['integrate_ms_mean']:.1f} integrating | "
                        f"max rel. diff. {report['max_relative_difference_corrected']:.2g} |")
            if number == 0 and name == "defaults":
                before, after = study.maps[0], study.maps[1]
                save_maps_side_by_side(
                    [(f"without correction: double surface {before.double_surface:.3f}", before.mapper.voxels()),
                     (f"corrected: double surface {after.double_surface:.3f}", after.mapper.voxels())],
                    dataset.label_map, before.mapper.resolution, out / "drift.png",
                    f"drift drive {seed}: the loop closes at scan {closure.closure_frame}, the odometry "
                    f"{study.drift_m:.2f} m off")
            print(f"seed {seed} {name}: done", flush=True)
    (out / "study.json").write_text(json.dumps(results, indent=2) + "\n")
    print("| drive | set-up | map | mIoU | double surface | labels equal (%) |")
    print("|---|---|---|---|---|---|")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
