"""``train``: the command line of the trainer (``training.trainer``): learn kernel lengths on
SemanticKITTI-format sequences and write a kernel file with pictures of the loss and kernels."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from convbki_core.datasets import parse_frames
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.devices import resolve_device
from convbki_core.io.kernel_file import save_kernel_file
from convbki_core.tools.cli import (
    NewOutputs,
    UserError,
    device_arg,
    frames_arg,
    output_folder,
    positive,
    progress,
    run,
    sequence_arg,
)
from convbki_core.training.trainer import train_kernel

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
    p.add_argument("--epochs", default=1, type=positive(int, "epochs"), metavar="N",
                   help="passes over the training samples (default: %(default)s)")
    p.add_argument("--lr", default=0.007, type=positive(float, "lr"), metavar="LR",
                   help="Adam learning rate (default: %(default)s)")
    p.add_argument("--frames", default=None, metavar="A:B", type=frames_arg,
                   help="use only scans A (inclusive) to B (exclusive) of each sequence; default: all")
    p.add_argument("--predictions-dir", default="predictions", metavar="DIR",
                   help="input segmentation folder under sequences/SS (default: %(default)s)")
    p.add_argument("--probabilities-dir", default=None, metavar="DIR",
                   help="train on per-point class probabilities (.npy) from this folder instead of labels")
    p.add_argument("--resolution", default=0.2, type=positive(float, "resolution"), metavar="M",
                   help="voxel edge in metres (default: %(default)s)")
    p.add_argument("--filter-size", default=5, type=int, metavar="F",
                   help="odd filter size in voxels (default: %(default)s)")
    p.add_argument("--seed", default=0, type=int, help="shuffling seed (default: %(default)s)")
    p.add_argument("--device", default="cpu", type=device_arg,
                   help="torch device to train on: cpu, auto (CUDA when present) or cuda[:N] (default: %(default)s)")
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
    datasets = [SemanticKittiSequence(args.dataset, sequence, args.predictions_dir, args.probabilities_dir)
                for sequence in args.sequences]
    for dataset in datasets:
        if not dataset.has_ground_truth:
            raise UserError(f"{dataset.folder}: no labels/ folder: training needs ground truth")
        if dataset.predictions_folder is None and dataset.probabilities_folder is None:
            raise UserError(f"{dataset.folder}: no input segmentation (give --predictions-dir or --probabilities-dir)")
    try:
        positions = [parse_frames(args.frames, len(dataset)) for dataset in datasets]
    except ValueError as error:
        raise UserError(str(error)) from None
    for dataset, chosen in zip(datasets, positions):
        dataset.check_files(chosen)  # before hours of training, not at the scan that is broken
    started = time.perf_counter()
    kernel, losses = train_kernel(datasets, positions, args.kernel, args.frames_per_sample, args.epochs, args.lr,
                                  args.resolution, args.filter_size, seed=args.seed,
                                  progress=None if args.quiet else _progress, log=_log(args.quiet),
                                  device=resolve_device(args.device))
    if not losses:
        raise UserError("no training sample had scored points (check labels and predictions)")
    save_kernel_file(kernel.to_config(), outputs.file(out))

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
    config = kernel.to_config()
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


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    return run(PROG, _train, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
