"""``train``: the command line of the trainer (``training.trainer``): learn kernel lengths on
SemanticKITTI-format sequences and write a kernel file with pictures of the loss and kernels.

Defaults (the trainer's module docstring has the details): samples shuffled; validation
frames held out of the training sequences (every 4th block of 10 frames, at most 20 frames,
2 frames of gap to the training frames) or ``--val-sequences``; the start kernel is
``--init FILE`` or every length 0.5 m; epochs sized to about 300 optimiser steps; cosine
learning-rate decay from ``--lr`` to 5 % of it; the kernel with the best validation mIoU
(the paper's protocol) is written, the start kernel when no trained kernel beats it
(``--strict``: refuse instead, exit 2). With ``--learn-free-ell`` the free-space length
``free_ell`` is learned too: besides the paper's point loss, each sample asks whether points
on the scan's rays in front of its returns are free in the past scans' map, and whether its
returns' voxels are not (``training.free_samples``); the value after the last step is written.
Without it the start kernel's ``free_ell`` is kept: a longer free kernel clears more trails
but empties real surface and multiplies the free-space pass's time. With probability inputs,
the temperature that calibrates them is fitted on the validation frames for the written lengths (the lowest map NLL that
costs at most ``--temperature-miou-loss`` of validation mIoU) and written as the kernel's
``temperature`` (``--keep-temperature``: the start's)."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from convbki_core.config import DEFAULTS
from convbki_core.datasets import parse_frames
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.devices import resolve_device
from convbki_core.inference.kernels import ConvBKIKernel
from convbki_core.io.kernel_file import load_kernel_file, save_kernel_file
from convbki_core.tools.cli import (
    NewOutputs,
    UserError,
    device_arg,
    frames_arg,
    non_negative,
    output_folder,
    positive,
    progress,
    run,
    say_notices,
    sequence_arg,
    window_bounds,
)
from convbki_core.training.objective import FREE_WEIGHT
from convbki_core.training.temperature_fit import TEMPERATURE_MIOU_LOSS, fit_temperature
from convbki_core.training.trainer import MIN_CLASS_POINTS, TARGET_UPDATES, train_kernel
from convbki_core.training.validation import (
    VALIDATION_BLOCK,
    VALIDATION_EVERY,
    VALIDATION_FRAMES,
    VALIDATION_GAP,
    Validator,
    split_validation,
)

PROG = "train"


def _progress(items, total: int, description: str):
    return progress(items, total=total, description=description)


def _log(quiet: bool):
    """Loss lines go to stderr beside the progress bar, to stdout when quiet."""
    return lambda message: print(message, file=sys.stdout if quiet else sys.stderr)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Learn the kernel lengths of a ConvBKI layer on SemanticKITTI-format sequences and write them "
        "as a kernel file, with a PNG of the loss curve and of the learned road and pole kernels. Train on "
        "sequences other than those you score on.")
    p.add_argument("--dataset", required=True, metavar="ROOT",
                   help="dataset root holding sequences/SS/{velodyne,labels,predictions,...}, poses.txt, calib.txt")
    p.add_argument("--sequences", required=True, nargs="+", metavar="SS", type=sequence_arg,
                   help="training sequence ids, e.g. 00 01")
    p.add_argument("--kernel", default="compound", choices=("single", "per_class", "compound"),
                   help="kernel variant to learn: single (one length ell), per_class (one ell per class) or "
                   "compound (horizontal ell_h and vertical ell_z per class) (default: %(default)s)")
    p.add_argument("--out", required=True, metavar="FILE", help="kernel file (YAML) to write; the loss curve and "
                   "kernel pictures go next to it as FILE_loss.png and FILE_kernels.png")
    p.add_argument("--frames-per-sample", default=10, type=positive(int, "frames-per-sample"), metavar="T",
                   help="scans per training sample: the current scan and T-1 past scans moved into its frame "
                   "(default: %(default)s)")
    p.add_argument("--epochs", default=None, type=positive(int, "epochs"), metavar="N",
                   help=f"passes over the training samples (default: enough for about {TARGET_UPDATES} steps)")
    p.add_argument("--lr", default=0.007, type=positive(float, "lr"), metavar="LR",
                   help="initial Adam learning rate; it decays along a cosine to 5%% of it at the last step "
                   "(default: %(default)s)")
    p.add_argument("--init", default=None, metavar="FILE",
                   help="start from this kernel file (same kind, resolution and filter size); default: every "
                   "length 0.5 m (free_ell, when learned, starts at no less than 1.25 voxels)")
    p.add_argument("--val-sequences", nargs="+", default=None, metavar="SS", type=sequence_arg,
                   help="validate on these sequences (at most --val-frames of their frames, in blocks) instead of "
                   f"holding out every {VALIDATION_EVERY}th block of {VALIDATION_BLOCK} frames of the training "
                   f"sequences (with {VALIDATION_GAP} frames of gap to the training frames)")
    p.add_argument("--val-frames", default=VALIDATION_FRAMES, type=positive(int, "val-frames"), metavar="N",
                   help="at most this many validation frames (default: %(default)s)")
    p.add_argument("--validate-every", default=None, type=positive(int, "validate-every"), metavar="M",
                   help="score the kernel on the validation frames every M steps (default: about 10 times a run, "
                   "plus the start and the last step)")
    p.add_argument("--strict", action="store_true",
                   help="refuse (exit 2, nothing written) when no trained kernel beats the start on validation; "
                   "by default the start kernel is written then")
    p.add_argument("--frames", default=None, metavar="A:B", type=frames_arg,
                   help="use only scans A (inclusive) to B (exclusive) of each sequence; default: all")
    p.add_argument("--predictions-dir", default="predictions", metavar="DIR",
                   help="input segmentation folder under sequences/SS (default: %(default)s)")
    p.add_argument("--probabilities-dir", default=None, metavar="DIR",
                   help="train on per-point class probabilities (.npy) from this folder instead of labels; the "
                   "temperature that calibrates them is then fitted on the validation frames and written")
    p.add_argument("--learn-free-ell", action="store_true",
                   help="also learn the free-space length free_ell from free-space questions in the samples; a longer "
                   "free kernel clears more trails of movers but empties real surface and makes the free-space pass "
                   "several times slower, so by default the start kernel's free_ell (none: one voxel) is kept")
    p.add_argument("--free-weight", default=FREE_WEIGHT, type=non_negative(float), metavar="W",
                   help="weight of the free-space question (mean NLL that points the scan saw through are free) "
                   "against the paper's point loss when free_ell is learned; larger values clear more trails of "
                   "movers and empty more real surface (default: %(default)s)")
    p.add_argument("--min-class-points", default=None, type=non_negative(int), metavar="N",
                   help="a class with fewer ground-truth points than this in the training frames keeps the start "
                   "kernel's lengths: with labels as input, the few objects such a class has in one drive make its "
                   "learned lengths fit them and cost that class on other drives; 0 learns every class (default: "
                   f"{MIN_CLASS_POINTS} with labels, 0 with --probabilities-dir, where every point's row trains "
                   "every class and the floor cost mIoU and calibration)")
    p.add_argument("--temperature-miou-loss", default=TEMPERATURE_MIOU_LOSS, type=non_negative(float), metavar="M",
                   help="with --probabilities-dir: the validation mIoU the fitted temperature may cost (a fraction; "
                   "sharpening soft probabilities calibrates the map but can change its labels); inf: no bound "
                   "(default: %(default)s)")
    p.add_argument("--keep-temperature", action="store_true",
                   help="with --probabilities-dir: do not fit the temperature; write the start kernel's (none: the "
                   "probabilities as given)")
    p.add_argument("--resolution", default=0.2, type=positive(float, "resolution"), metavar="M",
                   help="voxel edge in metres (default: %(default)s)")
    p.add_argument("--filter-size", default=5, type=int, metavar="F",
                   help="odd filter size in voxels (default: %(default)s)")
    p.add_argument("--seed", default=0, type=int, help="shuffling seed (default: %(default)s)")
    p.add_argument("--device", default=DEFAULTS.compute.device, type=device_arg,
                   help="torch device to train on: cpu, auto (CUDA when present) or cuda[:N] (default: %(default)s)")
    p.add_argument("--local-bounds", nargs=6, type=float, default=None, metavar=("XMIN", "YMIN", "ZMIN", "XMAX",
                   "YMAX", "ZMAX"), help="validation map window around the sensor in metres (default: the paper's "
                   "-40 -40 -2.6 40 40 2.6)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def _train(args: argparse.Namespace) -> int:
    outputs = NewOutputs()
    try:
        return _train_into(args, outputs)
    except BaseException:
        outputs.discard()  # a failed run leaves no kernel file or picture of its own
        raise


def _train_into(args: argparse.Namespace, outputs: NewOutputs) -> int:
    if args.filter_size < 1 or args.filter_size % 2 == 0:
        raise UserError(f"--filter-size must be a positive odd integer, got {args.filter_size}")
    out = Path(args.out)
    output_folder(out, "output")
    if out.is_dir():
        raise UserError(f"{out}: is a folder; --out names the kernel file to write")
    start = _start_kernel(args)
    datasets = [_dataset(args, sequence) for sequence in args.sequences]
    try:
        positions = [parse_frames(args.frames, len(dataset)) for dataset in datasets]
    except ValueError as error:
        raise UserError(str(error)) from None
    for dataset, chosen in zip(datasets, positions):
        dataset.check_files(chosen)  # before hours of training, not at the scan that is broken
    if args.val_sequences:
        overlap = sorted(set(args.val_sequences) & set(args.sequences))
        if overlap:
            raise UserError(f"--val-sequences {' '.join(overlap)} also in --sequences: validation must be held out")
        val_datasets = [_dataset(args, sequence) for sequence in args.val_sequences]
        _, val_positions = split_validation([range(len(d)) for d in val_datasets], every=1, gap=0,
                                            max_frames=args.val_frames)
        train_positions = positions
    else:
        val_datasets = datasets
        train_positions, val_positions = split_validation(positions, max_frames=args.val_frames)
        if not any(val_positions):
            raise UserError("too few frames to hold out validation frames: give more frames or --val-sequences")
    if not any(train_positions):
        raise UserError("no training frames left after holding out validation: give more frames or --val-sequences")
    if args.val_sequences:
        for dataset, chosen in zip(val_datasets, val_positions):
            dataset.check_files(chosen)
    bounds = window_bounds(args.local_bounds)
    device = resolve_device(args.device)
    validation_config = DEFAULTS.replace(device=str(device), forget_movers=False,
                                         local_bounds=bounds or DEFAULTS.window.local_bounds)
    validator = Validator(val_datasets, val_positions, validation_config)
    held = ", ".join(f"{d.sequence}: {_ranges(c)}" for d, c in zip(val_datasets, val_positions) if c)
    print(f"validation: {validator.frame_count} frames ({held}); training: "
          f"{sum(len(c) for c in train_positions)} samples")
    started = time.perf_counter()
    floor = _min_class_points(args)
    result = train_kernel(datasets, train_positions, args.kernel, args.frames_per_sample, args.epochs, args.lr,
                          args.resolution, args.filter_size, seed=args.seed,
                          progress=None if args.quiet else _progress, log=_log(args.quiet), device=device,
                          start=start, validator=validator, validate_every=args.validate_every,
                          learn_free_ell=args.learn_free_ell, free_weight=args.free_weight,
                          min_class_points=floor)
    losses = result.losses
    if not losses:
        raise UserError("no training sample had scored points (check labels and predictions)")
    print(f"validation mIoU: start {result.start_miou:.4f}, best {result.best_miou:.4f} "
          f"(step {result.best_step} of {result.total_steps}, {result.epochs} epochs)")
    if result.kept_classes:
        names = datasets[0].label_map.class_names
        print(f"kept at the start (under {floor} ground-truth points in the training frames): "
              + ", ".join(names[c] for c in result.kept_classes))
    if result.free_ells:
        print(f"free_ell: learned {result.free_ells[-1]:.4f} m (from {result.free_ells[0]:.4f} m after the first "
              f"step; start kernel: {_length(result.start.free_ell)})")
    if not result.improved:
        if args.strict:
            raise UserError(f"no trained kernel beat the start kernel on validation (mIoU {result.start_miou:.4f}); "
                            "nothing written (--strict)")
        print(f"no trained kernel beat the start kernel on validation (mIoU {result.start_miou:.4f}): "
              "writing the start kernel" + (" with the learned free_ell" if result.free_ells else ""))
    if args.probabilities_dir and not args.keep_temperature:
        bound = None if args.temperature_miou_loss == float("inf") else args.temperature_miou_loss
        fit = fit_temperature(validator, result.config, log=_log(args.quiet), miou_loss=bound)
        result.config.temperature = None if fit.temperature == 1.0 else fit.temperature
        within = "" if bound is None else f" within {bound:g} mIoU of the start's"
        print(f"temperature {fit.temperature:.4f} (start {fit.start_temperature:g}), the lowest map NLL on the "
              f"validation frames{within}: map NLL {fit.map_nll_before:.4f} -> {fit.map_nll_after:.4f}, ECE "
              f"{fit.map_ece_before:.4f} -> {fit.map_ece_after:.4f}, mIoU {fit.miou_before:.4f} -> "
              f"{fit.miou_after:.4f}; input NLL {fit.input_nll_before:.4f} -> {fit.input_nll_after:.4f}")
        print(f"  without the mIoU bound: T {fit.search.temperature:.4f}, map NLL {fit.search.value:.4f}, ECE "
              f"{fit.unbounded_ece:.4f}, mIoU {fit.unbounded_miou:.4f}; the input's own NLL would pick T "
              f"{fit.input_temperature:.4f} (input NLL {fit.input_nll_best:.4f})")
    kernel = ConvBKIKernel.from_config(result.config)
    save_kernel_file(result.config, outputs.file(out))

    from convbki_core.tools.plots import save_kernel_picture, save_loss_curve

    names = datasets[0].label_map.class_names
    loss_png = out.with_name(out.stem + "_loss.png")
    kernels_png = out.with_name(out.stem + "_kernels.png")
    save_loss_curve(losses, outputs.file(loss_png), f"{args.kernel} kernel, sequences {' '.join(args.sequences)}")
    save_kernel_picture(kernel, [names.index("road"), names.index("pole")], names, outputs.file(kernels_png))
    elapsed = time.perf_counter() - started
    tenth = max(1, len(losses) // 10)
    print(f"{len(losses)} steps in {elapsed:.0f} s ({elapsed / len(losses):.2f} s a step); loss "
          f"{np.mean(losses[:tenth]):.4f} (first tenth) -> {np.mean(losses[-tenth:]):.4f} (last tenth)")
    curve = [f"{np.mean(chunk):.3f}" for chunk in np.array_split(np.asarray(losses), min(10, len(losses)))]
    print("loss curve (10 segments): " + " ".join(curve))
    config = result.config
    if config.kernel == "compound":
        for name in ("road", "pole", "car", "building", "vegetation"):
            c = names.index(name)
            print(f"  {name:<11} ell_h {config.ell_h[c]:.3f} m  ell_z {config.ell_z[c]:.3f} m")
    elif config.kernel == "per_class":
        print("  " + ", ".join(f"{names[c]} {config.ell[c]:.3f}" for c in range(1, len(names))))
    else:
        print(f"  ell {config.ell[0]:.3f} m")
    print(f"kernel: {out}; pictures: {loss_png}, {kernels_png}")
    return 0


def _dataset(args: argparse.Namespace, sequence: str) -> SemanticKittiSequence:
    dataset = SemanticKittiSequence(args.dataset, sequence, args.predictions_dir, args.probabilities_dir)
    say_notices(PROG, dataset.notices)
    if not dataset.has_ground_truth:
        raise UserError(f"{dataset.folder}: no labels/ folder: training needs ground truth")
    if dataset.predictions_folder is None and dataset.probabilities_folder is None:
        raise UserError(f"{dataset.folder}: no input segmentation (give --predictions-dir or --probabilities-dir)")
    return dataset


def _start_kernel(args: argparse.Namespace):
    """The --init kernel file, checked against the other options; None: the trainer's default start."""
    if args.init is None:
        return None
    config = load_kernel_file(args.init)
    for name, wanted in (("kernel", args.kernel), ("resolution", args.resolution),
                         ("filter_size", args.filter_size)):
        if getattr(config, name) != wanted:
            flag = "--" + name.replace("_", "-")
            raise UserError(f"{args.init}: {name} {getattr(config, name)}, but {flag} is {wanted}")
    return config


def _min_class_points(args: argparse.Namespace) -> int:
    if args.min_class_points is not None:
        return args.min_class_points
    return 0 if args.probabilities_dir else MIN_CLASS_POINTS


def _length(value: float | None) -> str:
    return "one voxel" if value is None else f"{value:.4f} m"


def _ranges(positions) -> str:
    """Frames 30 31 32 40 41 -> '30-32 40-41'."""
    parts, first = [], None
    for index, position in enumerate(positions):
        if first is None:
            first = position
        if index + 1 == len(positions) or positions[index + 1] != position + 1:
            parts.append(f"{first}-{position}" if position != first else f"{first}")
            first = None
    return " ".join(parts)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    return run(PROG, _train, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
