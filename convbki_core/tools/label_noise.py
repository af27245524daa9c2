"""``label_noise``: an input segmentation for labelled real scans, made by a noise model.

Real SemanticKITTI scans have ground truth but no network predictions. This command writes
OUTROOT/sequences/SS/ as a dataset that ``evaluate`` and ``kitti_to_bag`` read: symbolic
links to the source's velodyne/, labels/, poses.txt, calib.txt and times.txt, a real folder
``<predictions-dir>/NNNNNN.label`` with the noisy labels (raw ids, instance bits 0) and
``label_noise.json`` (target and measured input mIoU, IoU per class, the strength found, the
seed, the model's version, the objects it confused). With OUTROOT equal to ROOT only the
predictions folder and the json are written. The model (object confusions inside confusion
groups, boundary blur, range-dependent confusions) is documented in
``convbki_core.datasets.label_noise``; its strength is calibrated so that the written input's
mIoU meets ``--input-miou``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import shutil
import stat
import sys
import tempfile
from collections.abc import Iterable, Sequence
from pathlib import Path

from convbki_core.tools.cli import UserError, frames_arg, run, sequence_arg

PROG = "label_noise"
LINKED = ("velodyne", "labels", "poses.txt", "calib.txt", "times.txt")
JSON_NAME = "label_noise.json"
# Sequences with more points than this are calibrated on a weighted sample (memory), then
# measured exactly while written.
EXACT_POINTS = 12_000_000
SAMPLE_POINTS = 6_000_000


def _miou_arg(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and 0.0 < value <= 1.0):
        raise argparse.ArgumentTypeError(f"--input-miou must be a fraction in (0, 1], got {text!r}")
    return value


def _seed_arg(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--seed must be a whole number, got {text!r}") from None


def _folder_name_arg(text: str) -> str:
    if not text or "/" in text or os.sep in text or text.startswith(".") or text in LINKED or text == JSON_NAME:
        raise argparse.ArgumentTypeError(
            f"--predictions-dir must be a plain folder name (not {', '.join(LINKED)}), got {text!r}")
    return text


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Make an input segmentation for labelled SemanticKITTI-format scans from their ground truth "
        "with a documented noise model (not a network): per-object persistent confusions inside confusion "
        "groups (vehicles, two-wheelers, people), so that objects' labels flicker from scan to scan; boundary "
        "blur; range-dependent confusions, partly persistent in the world frame. One strength scales every "
        "rate and is calibrated by bisection so that the written input's mIoU meets --input-miou. Writes "
        "OUTROOT/sequences/SS/ with links to the source's scans, labels, poses, calib and times, the noisy "
        f"labels in <predictions-dir>/ and {JSON_NAME}. The model: convbki_core/datasets/label_noise.py.",
        epilog="Example: label_noise --dataset /data/semantic_kitti/dataset --sequence 05 --out "
        "out/real_noisy; then evaluate --dataset out/real_noisy --sequence 05 --report r.json")
    p.add_argument("--dataset", required=True, metavar="ROOT",
                   help="SemanticKITTI-layout root with ROOT/sequences/SS/{velodyne,labels,poses.txt,calib.txt}; "
                   "only read, never written (unless --out is ROOT itself)")
    p.add_argument("--sequence", required=True, metavar="SS", type=sequence_arg, help="sequence id, e.g. 05")
    p.add_argument("--out", required=True, metavar="OUTROOT",
                   help="dataset root to write OUTROOT/sequences/SS/ into (links to the source's files, the "
                   f"predictions folder, {JSON_NAME}); when it is ROOT itself only the predictions folder and "
                   f"{JSON_NAME} are written. An existing predictions folder is replaced only when an earlier "
                   f"label_noise run wrote it ({JSON_NAME} names it)")
    p.add_argument("--input-miou", default=0.55, type=_miou_arg, metavar="M",
                   help="target mIoU of the input segmentation (fraction in (0, 1]; class 0 ignored, mean over "
                   "the classes present in the ground truth of the written frames); the noise strength is "
                   "calibrated by bisection to meet it within about 0.01, and the exact mIoU of what is written is "
                   "reported; a target out of reach is an error (default: %(default)s)")
    p.add_argument("--seed", default=0, type=_seed_arg, metavar="S",
                   help="seed of every noise draw: the same seed, sequence and frames write the same files, byte "
                   "for byte (default: %(default)s)")
    p.add_argument("--predictions-dir", default="predictions", type=_folder_name_arg, metavar="DIR",
                   help="folder name, inside OUTROOT/sequences/SS, of the written input segmentation "
                   "(NNNNNN.label, uint32 raw SemanticKITTI ids, instance bits 0); pass the same name to evaluate "
                   "(default: %(default)s)")
    p.add_argument("--frames", default=None, metavar="A:B", type=frames_arg,
                   help="write only frames A (inclusive) to B (exclusive), e.g. 0:5; calibration and the "
                   "measured mIoU cover exactly these frames (default: all)")
    p.add_argument("--quiet", action="store_true", help="no progress bar and no summary")
    return p


def _progress(items: Iterable, total: int, description: str, quiet: bool) -> Iterable:
    if quiet:
        return items
    from convbki_core.tools.cli import progress

    return progress(items, total=total, description=f"{PROG}: {description}")


def _check_destination(source: Path, out_seq: Path, predictions_dir: str) -> bool:
    """Refuse, before any work, what the run cannot or must not write; True when writing in place."""
    if out_seq.exists() and not out_seq.is_dir():
        raise UserError(f"{out_seq}: not a folder")
    in_place = out_seq.is_dir() and out_seq.samefile(source)
    if not in_place:
        for name in LINKED:
            target, link = source / name, out_seq / name
            if not (link.exists() or link.is_symlink()):
                continue
            if not (link.is_symlink() and target.exists() and link.resolve() == target.resolve()):
                raise UserError(f"{link}: exists and is not a link to {target}; choose another --out")
    final = out_seq / predictions_dir
    if final.exists() or final.is_symlink():
        written_by_us = False
        with contextlib.suppress(OSError, ValueError, AttributeError):
            written_by_us = json.loads((out_seq / JSON_NAME).read_text()).get("predictions_dir") == predictions_dir
        if final.is_symlink() or not final.is_dir() or not written_by_us:
            raise UserError(f"{final}: exists and was not written by {PROG}; choose another --predictions-dir "
                            "or --out")
    existing = next(p for p in (out_seq, *out_seq.parents) if p.exists())
    if not existing.is_dir():
        raise UserError(f"{existing}: not a folder (for {out_seq})")
    # The permission bits too: a superuser may write anywhere, but a folder marked read-only (a
    # shared data set) is not to be written into by this command.
    if not os.access(existing, os.W_OK | os.X_OK) or not existing.stat().st_mode & stat.S_IWUSR:
        raise UserError(f"{existing}: not writable (read-only folder); choose another --out")
    return in_place


def _label_noise(args: argparse.Namespace) -> int:
    import numpy as np

    from convbki_core.datasets import DatasetError, parse_frames
    from convbki_core.datasets import label_noise as model_module
    from convbki_core.datasets.label_noise_calibration import calibrate, sample_draws
    from convbki_core.datasets.semantic_kitti import SemanticKittiSequence, read_label_words
    from convbki_core.io.atomic import atomic_write_bytes, remove_stale_staging_folders, staging_prefix
    from convbki_core.io.labels import load_label_map
    from convbki_core.measures.metrics import ConfusionMatrix
    from convbki_core.synth.lidar import MissingDependency, require_numba
    from convbki_core.tools.cli import NewOutputs, say_notices

    try:
        require_numba()
    except MissingDependency as error:
        raise UserError(str(error)) from None
    label_map = load_label_map("semantic_kitti")
    dataset = SemanticKittiSequence(args.dataset, args.sequence, predictions_dir=None, label_map=label_map)
    say_notices(PROG, dataset.notices)
    if not dataset.has_ground_truth:
        raise DatasetError(f"{dataset.labels_folder}: no labels folder, so there is nothing to make an input from")
    try:
        positions = parse_frames(args.frames, len(dataset))
    except ValueError as error:
        raise UserError(str(error)) from None
    dataset.check_files(positions)
    source = dataset.folder.resolve()
    out_seq = Path(args.out) / "sequences" / dataset.sequence
    in_place = _check_destination(source, out_seq, args.predictions_dir)

    model = model_module.LabelNoiseModel(label_map, args.seed, dataset.sequence)

    def draws_of(position: int):
        frame = dataset[position]
        words = read_label_words(dataset.labels_folder / f"{frame.name}.label")
        return frame, model.draws(frame, words >> np.uint32(16))

    # Pass 1: the draws of every frame (strength-independent); whole, or a weighted sample of a long sequence.
    total_points = sum((dataset.scan_files[p].stat().st_size // 16) for p in positions)
    exact = total_points <= EXACT_POINTS
    kept, weights, names = [], [], []
    rng = np.random.default_rng(model_module._salt(args.seed, dataset.sequence, "calibration-sample"))
    per_class = max(50, SAMPLE_POINTS // (len(positions) * 16))
    for position in _progress(positions, len(positions), "drawing", args.quiet):
        frame, draws = draws_of(position)
        names.append(frame.name)
        if exact:
            kept.append(draws)
        else:
            sample, weight = sample_draws(draws, per_class, rng)
            kept.append(sample)
            weights.append(weight)
    everything = model_module.ScanDraws.join(kept)
    weight = None if exact else np.concatenate(weights)

    # Calibration: bisection on the strength.
    bar = None
    if not args.quiet:
        from tqdm import tqdm

        bar = tqdm(desc=f"{PROG}: calibrating", unit="step", file=sys.stderr, dynamic_ncols=True)

    def step(strength: float, value: float) -> None:
        if bar is not None:
            bar.set_postfix_str(f"strength {strength:.4f} mIoU {value:.4f}")
            bar.update(1)

    try:
        calibration = calibrate(model, everything, args.input_miou, weight, on_step=step)
    finally:
        if bar is not None:
            bar.close()
    if not calibration.reachable:
        raise UserError(f"input mIoU {args.input_miou:g} is out of reach on these frames: the nearest the noise model "
                        f"gets is {calibration.miou:.4f} (strength {calibration.strength:.4g})")
    strength = calibration.strength
    del kept

    # Pass 2: predict and write; the measured mIoU is exact over every written point.
    scores = ConfusionMatrix(label_map.num_classes, label_map.ignore_classes)
    wrong_by_mechanism = np.zeros(len(model_module.MECHANISMS), np.int64)
    objects: dict[int, dict] = {}
    outputs = NewOutputs()
    final = out_seq / args.predictions_dir
    stage = None
    try:
        outputs.folder(out_seq)
        if not in_place:
            for name in LINKED:
                target, link = source / name, out_seq / name
                if target.exists() and not link.is_symlink():
                    os.symlink(target, link, target_is_directory=target.is_dir())
                    outputs.created.append(link)
        remove_stale_staging_folders(final)
        stage = Path(tempfile.mkdtemp(dir=out_seq, prefix=staging_prefix(final)))
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(stage, 0o777 & ~umask)  # mkdtemp makes it private; the folder is the user's data
        offset = 0
        for index, position in enumerate(_progress(positions, len(positions), "writing", args.quiet)):
            if exact:
                count = int(dataset.scan_files[position].stat().st_size // 16)
                draws = everything.subset(slice(offset, offset + count))
                offset += count
            else:
                draws = draws_of(position)[1]
            predicted, mechanism = model.predict(draws, strength)
            truth = draws.truth.astype(np.int64)
            scores.add(truth, predicted)
            wrong = (truth > 0) & (predicted != truth)
            wrong_by_mechanism += np.bincount(mechanism[wrong], minlength=len(wrong_by_mechanism))
            _note_objects(objects, model, draws, predicted, mechanism, strength, names[index])
            raw = label_map.to_raw(predicted).astype("<u4")
            atomic_write_bytes(stage / f"{names[index]}.label", raw.tobytes())
        if final.exists():
            old = out_seq / (staging_prefix(final) + "replaced")
            os.rename(final, old)
            os.rename(stage, final)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.rename(stage, final)
            outputs.created.append(final)
        stage = None
        summary = scores.summary(label_map.class_names)
        report = {
            "tool": PROG, "model": "convbki_core.datasets.label_noise", "model_version": model_module.MODEL_VERSION,
            "source": str(source), "sequence": dataset.sequence, "predictions_dir": args.predictions_dir,
            "frames": {"first": names[0], "last": names[-1], "count": len(names), "spec": args.frames or ":"},
            "seed": args.seed, "target_miou": args.input_miou, "measured_miou": summary["miou"],
            "accuracy": summary["accuracy"], "strength": strength,
            "calibration": "exact: every written point" if exact else "weighted sample of the written points",
            "iou": summary["iou"], "points": int(scores.counts.sum()),
            "wrong_points_by_mechanism": {name: int(n) for name, n in zip(model_module.MECHANISMS,
                                                                           wrong_by_mechanism) if name != "none"},
            "instance_bits": "0: the input carries no instance ids",
            "moving_ids": "none: moving objects are written with their static class's raw id",
            "confused_objects": _object_list(objects, label_map.class_names),
            "objects": len(objects),
        }
        atomic_write_bytes(out_seq / JSON_NAME, (json.dumps(report, indent=2) + "\n").encode())
    except BaseException:
        if stage is not None:
            shutil.rmtree(stage, ignore_errors=True)
        outputs.discard()
        raise
    if not args.quiet:
        iou = ", ".join(f"{name} {value:.2f}" for name, value in summary["iou"].items())
        confused = report["confused_objects"]
        print(f"wrote {len(names)} frames to {final} and {out_seq / JSON_NAME}\n"
              f"  input mIoU:  {summary['miou']:.4f} (target {args.input_miou:g}; accuracy {summary['accuracy']:.3f}; "
              f"strength {strength:.4f})\n"
              f"  input IoU:   {iou}\n"
              f"  objects:     {len(confused)} of {len(objects)} confused inside their group")
        if not exact and abs(summary["miou"] - args.input_miou) > 0.01:
            print(f"{PROG}: warning: calibrated on a sample; the written mIoU is {summary['miou']:.4f}",
                  file=sys.stderr)
    return 0


def _note_objects(objects: dict, model, draws, predicted, mechanism, strength: float, scan: str) -> None:
    """Record, per object of the scan, its class and whether (and as what) the model confused it."""
    import numpy as np

    from convbki_core.datasets.label_noise import OBJECT

    on_object = draws.object_key >= 0
    if not on_object.any():
        return
    keys, first = np.unique(draws.object_key[on_object], return_index=True)
    where = np.flatnonzero(on_object)
    classes = keys & 0x1F
    rate = model.object_rate(classes, strength)
    for key, c, u, r in zip(keys, classes, draws.object_u[where[first]], rate):
        entry = objects.setdefault(int(key), {"class": int(c), "confused": bool(u < r), "scans": 0, "shown": {}})
        entry["scans"] += 1
        if entry["confused"]:
            mine = on_object & (draws.object_key == key) & (mechanism == OBJECT)
            if mine.any():
                shown = int(np.bincount(predicted[mine]).argmax())
                entry["shown"][shown] = entry["shown"].get(shown, 0) + 1


def _object_list(objects: dict, class_names: Sequence[str]) -> list[dict]:
    """The confused objects: instance id (None for things without one), true class, scans seen, and
    in how many scans each class was shown."""
    listed = []
    for key, entry in sorted(objects.items()):
        if not entry["confused"]:
            continue
        instance = key >> 5
        listed.append({"instance": instance if instance < 0x10000 else None, "class": class_names[entry["class"]],
                       "scans": entry["scans"],
                       "shown_in_scans": {class_names[c]: n for c, n in sorted(entry["shown"].items())}})
    return listed


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    return run(PROG, _label_noise, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
