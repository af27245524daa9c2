"""``map_tool`` (info, merge, export-ply) and ``evaluate --save-map`` on real map files."""

from __future__ import annotations

import json
import subprocess
import sys
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from helpers import read_ply, sorted_map
from kitti_fixture import write_drive

from convbki_core.config import DEFAULTS, MapperConfig
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.free_space.clamping import DEFAULT_LIMIT
from convbki_core.io import atomic
from convbki_core.io.map_file import MapSnapshot, read_map
from convbki_core.mapper import ConvBKIMapper
from convbki_core.memory.store import VoxelStore
from convbki_core.paths import kernel_path
from convbki_core.tools import evaluate, map_merge, map_tool
from convbki_core.tools.synth import main as synth

REPO = Path(__file__).resolve().parents[2]
BOUNDS = ((-20.0, -12.0, -3.0), (20.0, 12.0, 4.0))
FRAMES = 12
HALF = FRAMES // 2
PRIOR = 1e-3


def map_frames(dataset, start, stop, path, **options):
    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, prior=PRIOR, device="cpu", **options),
                           kernel_path("semantic_kitti_compound"))
    for position in range(start, stop):
        frame = dataset[position]
        mapper.integrate(frame.points, frame.input_values, frame.pose)
    mapper.save(path)
    return path


@pytest.fixture(scope="module")
def maps(tmp_path_factory):
    """A short synthetic drive (sparse 16-beam LiDAR, for speed) mapped as two halves and as a whole."""
    root = tmp_path_factory.mktemp("maps")
    assert synth(["--out", str(root / "data"), "--sequence", "08", "--frames", str(FRAMES), "--seed", "3",
                  "--beams", "16", "--azimuth-steps", "360", "--noise-strength", "0.35", "--quiet"]) == 0
    dataset = SemanticKittiSequence(root / "data", "08")
    labels = dataset.label_map
    product = {"free_space": True, "max_concentration": DEFAULT_LIMIT, "ignore_classes": labels.ignore_classes,
               "ground_classes": labels.ground_classes}  # the node's and evaluate's defaults
    return {"first": map_frames(dataset, 0, HALF, root / "first.npz"),
            "second": map_frames(dataset, HALF, FRAMES, root / "second.npz"),
            "whole": map_frames(dataset, 0, FRAMES, root / "whole.npz"),
            "product_first": map_frames(dataset, 0, HALF, root / "product_first.npz", **product),
            "product_second": map_frames(dataset, HALF, FRAMES, root / "product_second.npz", **product),
            "product_whole": map_frames(dataset, 0, FRAMES, root / "product_whole.npz", **product)}


def one_line_error(capsys) -> str:
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith("map_tool: error: ") and "Traceback" not in captured.err
    return lines[0]


def test_merge_of_two_halves_is_the_map_of_the_whole_drive(maps, tmp_path, capsys):
    out = tmp_path / "merged.npz"
    assert map_tool.main(["merge", str(maps["first"]), str(maps["second"]), "--out", str(out), "--quiet"]) == 0
    assert "merged 2 maps" in capsys.readouterr().out
    metadata, indices, alpha = sorted_map(out)
    _, whole_indices, whole_alpha = sorted_map(maps["whole"])
    _, first_indices, first_alpha = read_map(maps["first"])
    _, second_indices, _ = read_map(maps["second"])
    # The halves overlap in space, so the prior-counted-once rule is exercised on many voxels.
    shared = {tuple(v) for v in first_indices.tolist()} & {tuple(v) for v in second_indices.tolist()}
    assert len(shared) > 100
    np.testing.assert_array_equal(indices, whole_indices)
    # Not bit-exact: the whole-drive map adds each scan's increments one by one in float32, the merge adds
    # two partial sums, and float32 addition depends on the order of the terms.
    np.testing.assert_allclose(alpha, whole_alpha, rtol=1e-5, atol=0)
    # Voxels seen by one half only keep their rows bit for bit.
    only_first = np.array([tuple(v) not in shared for v in first_indices.tolist()])
    lookup = {tuple(v): row for row, v in enumerate(indices.tolist())}
    rows = [lookup[tuple(v)] for v in first_indices[only_first].tolist()]
    np.testing.assert_array_equal(alpha[rows], first_alpha[only_first])
    assert metadata["num_voxels"] == len(whole_indices) and metadata["scans_integrated"] == FRAMES
    assert metadata["merged_from"] == [str(maps["first"]), str(maps["second"])]


def test_maps_made_with_free_space_and_clamping_merge_into_the_labels_of_the_whole_drive(maps, tmp_path):
    """Clamping keeps the prior, so the product's own files merge. The merge adds the halves'
    evidence, which is not one mapper's in two ways, as the docs say: clamping is not a sum, and
    the second half's rays added no free evidence to the voxels only the first half held (free
    space reaches voxels that hold evidence in that mapper). So the labels differ, nearly all as
    voxels the whole drive's rays emptied that the merge leaves occupied."""
    out = tmp_path / "merged.npz"
    assert map_tool.main(["merge", str(maps["product_first"]), str(maps["product_second"]), "--out", str(out),
                          "--quiet"]) == 0
    _, indices, alpha = sorted_map(out)
    _, whole_indices, whole_alpha = sorted_map(maps["product_whole"])
    np.testing.assert_array_equal(indices, whole_indices)  # free space adds to voxels with evidence only
    assert alpha.min() >= np.float32(PRIOR)
    clamped = ~np.isclose(alpha.sum(axis=1), whole_alpha.sum(axis=1), rtol=1e-4)
    assert clamped.any()  # the drive has voxels where the two differ, or this proves nothing
    merged_labels, whole_labels = alpha.argmax(axis=1), whole_alpha.argmax(axis=1)
    differ = merged_labels != whole_labels
    assert differ.mean() <= 0.03, differ.mean()
    left_occupied = differ & (whole_labels == 0)
    assert left_occupied.sum() >= 0.9 * differ.sum(), (int(left_occupied.sum()), int(differ.sum()))


def test_merge_counts_the_prior_once(maps, tmp_path):
    """A plain sum of the halves (prior counted twice) is not the whole map: the test above can fail."""
    _, indices, _ = sorted_map(maps["whole"])
    parts = [read_map(maps[name])[1:] for name in ("first", "second")]
    merged_indices, merged, shared = map_merge.merge_arrays(parts, PRIOR)
    _, naive, _ = map_merge.merge_arrays(parts, 0.0)
    np.testing.assert_array_equal(merged_indices, indices)
    assert shared > 0 and not np.allclose(naive, merged, rtol=1e-5, atol=0)


def test_merge_refuses_an_existing_output_and_the_same_map_twice(maps, tmp_path, capsys):
    out = tmp_path / "merged.npz"
    out.write_bytes(b"keep me")
    assert map_tool.main(["merge", str(maps["first"]), str(maps["second"]), "--out", str(out), "--quiet"]) == 2
    assert "--force" in one_line_error(capsys) and out.read_bytes() == b"keep me"
    assert map_tool.main(["merge", str(maps["first"]), str(maps["second"]), "--out", str(out), "--force",
                          "--quiet"]) == 0
    assert read_map(out)[0]["merged_from"]
    again = tmp_path / "again.npz"
    assert map_tool.main(["merge", str(maps["first"]), str(maps["first"]), "--out", str(again), "--quiet"]) == 2
    assert "given twice" in one_line_error(capsys) and not again.exists()


@pytest.mark.parametrize("change, message", [
    ("resolution", "resolution (m) differs (0.2 vs 0.4)"),
    ("num_classes", "num_classes differs (20 vs 19)"),
    ("frame_id", "frame_id differs ('map' vs 'odom')"),
    ("prior", "prior differs (0.001 vs 0.01)"),
])
def test_merge_refuses_maps_that_do_not_add_up(maps, tmp_path, capsys, change, message):
    metadata, indices, alpha = read_map(maps["second"])
    if change == "resolution":
        metadata["resolution"] = 0.4
    elif change == "num_classes":
        metadata["num_classes"], alpha = 19, alpha[:, :19]
    elif change == "frame_id":
        metadata["frame_id"] = "odom"
    else:
        metadata["prior"], alpha = 0.01, alpha + 0.01
    other = tmp_path / "other.npz"
    MapSnapshot(metadata, indices, alpha).write(other)
    out = tmp_path / "merged.npz"
    assert map_tool.main(["merge", str(maps["first"]), str(other), "--out", str(out), "--quiet"]) == 2
    line = one_line_error(capsys)
    assert message in line and str(maps["first"]) in line and str(other) in line
    assert not out.exists() and not list(tmp_path.glob(".merged.npz*"))


def test_info_reports_what_the_file_holds(maps, capsys):
    _, indices, alpha = read_map(maps["whole"])
    assert map_tool.main(["info", str(maps["whole"]), "--json", "--quiet"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["num_voxels"] == len(indices) and info["num_classes"] == 20 and info["frame_id"] == "map"
    assert info["bounds"]["index_min"] == indices.min(axis=0).tolist()
    assert info["bounds"]["index_max"] == indices.max(axis=0).tolist()
    np.testing.assert_allclose(info["bounds"]["metres_min"], indices.min(axis=0) * 0.2)
    np.testing.assert_allclose(info["bounds"]["metres_max"], (indices.max(axis=0) + 1) * 0.2)
    counts = {entry["name"]: entry["voxels"] for entry in info["class_voxels"]}
    expected = np.bincount(alpha.argmax(axis=1), minlength=20)
    assert counts["road"] == expected[9] and sum(counts.values()) == len(indices)
    assert info["resolution"] == 0.2 and info["prior"] == PRIOR and info["kernel"] == "compound"
    assert info["scans_integrated"] == FRAMES and info["file_bytes"] == maps["whole"].stat().st_size
    # The memory of the store the map loads into, against an independent measure: the bytes Python
    # and numpy allocated (tracemalloc) for a store that holds the file's voxels and still holds
    # them, within 5 % (the allocator's block headers are estimated, not read).
    VoxelStore(20, prior=PRIOR).write(indices, alpha)  # anything a first write compiles or caches
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        store = VoxelStore(20, prior=PRIOR)
        store.write(indices, alpha)
        held = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert len(store) == len(indices)
    assert abs(info["memory_bytes"] - held) <= 0.05 * held, (info["memory_bytes"], held)
    # At least the compact rows: per voxel its offset (2 bytes) and class count (1), per class
    # above the prior its id (1) and value (4); dense float32 rows would be 80 bytes a voxel.
    entries = int((alpha != np.float32(PRIOR)).sum())
    assert 3 * len(indices) + 5 * entries <= info["memory_bytes"] < 80 * len(indices)
    assert info["bytes_per_voxel"] == round(info["memory_bytes"] / len(indices), 1) < 40
    assert map_tool.main(["info", str(maps["whole"]), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert f"voxels:      {len(indices)}\n" in text and "road" in text


def test_export_ply_writes_every_voxel_or_the_confident_ones(maps, tmp_path, capsys):
    _, indices, alpha = read_map(maps["whole"])
    ply = tmp_path / "map.ply"
    assert map_tool.main(["export-ply", str(maps["whole"]), "--out", str(ply), "--quiet"]) == 0
    assert f"wrote {len(indices)} voxels" in capsys.readouterr().out
    vertices = read_ply(ply)
    assert len(vertices) == len(indices)
    np.testing.assert_allclose(np.column_stack([vertices["x"], vertices["y"], vertices["z"]]),
                               (indices + 0.5) * 0.2, atol=1e-5)
    np.testing.assert_array_equal(vertices["label"], alpha.argmax(axis=1))
    # Variance of the expected class, computed here from the concentrations.
    total = alpha.astype(np.float64).sum(axis=1)
    expected = alpha.max(axis=1) / total
    variance = expected * (1 - expected) / (1 + total)
    limit = float(np.median(variance))
    confident = tmp_path / "confident.ply"
    assert map_tool.main(["export-ply", str(maps["whole"]), "--out", str(confident), "--max-variance",
                          str(limit), "--quiet"]) == 0
    kept = len(read_ply(confident))
    assert 0 < kept < len(indices)
    assert abs(kept - int((variance <= limit).sum())) <= 2  # float32 vs float64 at the boundary


@pytest.mark.parametrize("arguments, message", [
    ([], "required: COMMAND"),
    (["info", "{tmp}/nowhere.npz"], "no such map file"),
    (["info", "{tmp}/not_a_map.npz"], "not a"),
    (["export-ply", "{tmp}/nowhere.npz", "--out", "{tmp}/out.ply"], "no such map file"),
    (["export-ply", "{tmp}/not_a_map.npz", "--out", "{tmp}/missing/out.ply"], "output folder does not exist"),
    (["export-ply", "{tmp}/not_a_map.npz", "--out", "{tmp}/out.ply", "--max-variance", "-1"], "positive"),
    (["merge", "{tmp}/nowhere.npz", "--out", "{tmp}/out.npz"], "required: MAP"),
    (["merge", "{tmp}/nowhere.npz", "{tmp}/not_a_map.npz", "--out", "{tmp}/out.npz"], "no such map file"),
])
def test_cli_errors_are_one_line_and_exit_2(tmp_path, capsys, arguments, message):
    (tmp_path / "not_a_map.npz").write_bytes(b"this is text")
    arguments = [a.replace("{tmp}", str(tmp_path)) for a in arguments]
    assert exit_code([*arguments, "--quiet"] if arguments else arguments) == 2
    assert message in one_line_error(capsys)
    assert not (tmp_path / "out.ply").exists() and not (tmp_path / "out.npz").exists()


def exit_code(argv) -> int:
    """main()'s return value, or the code argparse exits with on a bad command line."""
    try:
        return map_tool.main(argv)
    except SystemExit as exit_:
        return exit_.code


def test_module_runs_as_a_process_without_traceback(tmp_path):
    result = subprocess.run([sys.executable, "-m", "convbki_core.tools.map_tool", "info",
                             str(tmp_path / "nowhere.npz")], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.strip().splitlines() == [f"map_tool: error: {tmp_path / 'nowhere.npz'}: no such map file"]


# -- evaluate --save-map -------------------------------------------------------------------
SMALL_WINDOW = ["--local-bounds", "-20", "-12", "-3", "20", "12", "4", "--device", "cpu"]


def test_evaluate_saves_the_map_it_built(tmp_path, capsys):
    write_drive(tmp_path / "data", "08", frames=4)
    saved = tmp_path / "final.npz"
    assert evaluate.main(["--dataset", str(tmp_path / "data"), "--sequence", "08", "--report",
                          str(tmp_path / "r.json"), "--save-map", str(saved), "--quiet", *SMALL_WINDOW]) == 0
    metadata, indices, alpha = sorted_map(saved)
    # The same frames through a mapper with evaluate's defaults: the same arithmetic, so the same bits.
    dataset = SemanticKittiSequence(tmp_path / "data", "08")
    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, prior=DEFAULTS.window.prior, device="cpu",
                                              ignore_classes=dataset.label_map.ignore_classes),
                           DEFAULTS.kernel_path())
    for frame in dataset:
        mapper.integrate(frame.points, frame.input_values, frame.pose)
    expected_indices, expected_alpha = mapper.items()
    order = np.lexsort(expected_indices.T[::-1])
    np.testing.assert_array_equal(indices, expected_indices[order])
    np.testing.assert_array_equal(alpha, expected_alpha[order])
    assert metadata["scans_integrated"] == 4 and len(indices) > 1000
    assert f"map: {saved} ({len(indices)} voxels)" in capsys.readouterr().out


def test_evaluate_save_map_refused_up_front_and_never_left_by_a_failed_run(tmp_path, capsys, monkeypatch):
    write_drive(tmp_path / "data", "08", frames=2)
    common = ["--dataset", str(tmp_path / "data"), "--sequence", "08", "--report", str(tmp_path / "r.json"),
              "--quiet", *SMALL_WINDOW]
    (tmp_path / "folder.npz").mkdir()
    for bad, message in ((tmp_path / "missing" / "map.npz", "folder does not exist"),
                         (tmp_path / "folder.npz", "is a folder")):
        assert evaluate.main([*common, "--save-map", str(bad)]) == 2
        error = capsys.readouterr().err.strip().splitlines()
        assert len(error) == 1 and message in error[0] and error[0].startswith("evaluate: error: ")
        assert not (tmp_path / "r.json").exists()

    def fail(path, data):
        raise OSError(28, "No space left on device", str(path))

    # The report is written after the map: when it fails, the run fails and takes its map with it.
    # (evaluate takes the writer from convbki_core.io.atomic when its run starts.)
    monkeypatch.setattr(atomic, "atomic_write_bytes", fail)
    saved = tmp_path / "final.npz"
    assert evaluate.main([*common, "--save-map", str(saved)]) == 2
    assert "No space left" in capsys.readouterr().err
    assert not saved.exists() and not list(tmp_path.glob(".final.npz*"))


def test_costmap_writes_the_grid_of_every_observed_column(maps, tmp_path, capsys):
    """The .npz holds column_costs of the map's voxels, cell for cell; the drive's road is
    mostly free for the car and its buildings lethal; the .png is a picture."""
    from convbki_core.costmap.columns import column_costs
    from convbki_core.costmap.grid import rasterise
    from convbki_core.costmap.profile import load_profile
    from convbki_core.io.labels import load_label_map
    from convbki_core.paths import traversability_profile

    out = tmp_path / "grid.npz"
    assert map_tool.main(["costmap", str(maps["whole"]), "--out", str(out), "--quiet"]) == 0
    assert "observed cells" in capsys.readouterr().out
    saved = np.load(out)
    metadata, indices, alpha = read_map(maps["whole"])
    names = load_label_map("semantic_kitti").class_names
    profile = load_profile(traversability_profile("car"), names)
    columns = column_costs(indices, alpha, metadata["resolution"], profile, metadata["prior"])
    grid = rasterise(columns, metadata["resolution"])
    np.testing.assert_array_equal(saved["values"], grid.values)
    np.testing.assert_allclose(saved["origin"], grid.origin_metres)
    assert str(saved["profile"]) == "car" and float(saved["resolution"]) == metadata["resolution"]
    # Columns whose ground voxel is surely road (p > 0.9) are mostly in the free group (<= 25).
    ground_of = dict(zip(map(tuple, columns.cells.tolist()), columns.ground.tolist()))
    costs = dict(zip(map(tuple, columns.cells.tolist()), columns.cost.tolist()))
    p = alpha / alpha.sum(axis=1, keepdims=True)
    road = [tuple(i[:2]) for i, share in zip(indices.tolist(), p[:, names.index("road")])
            if share > 0.9 and ground_of.get(tuple(i[:2])) == i[2]]
    free = np.mean([0 <= costs[cell] <= 25 for cell in road])
    assert len(road) > 100 and free > 0.8, (len(road), free)
    assert (grid.values == 100).sum() > 0 and (grid.values == -1).sum() > 0

    picture = tmp_path / "grid.png"
    assert map_tool.main(["costmap", str(maps["whole"]), "--out", str(picture), "--profile", "small_robot",
                          "--quiet"]) == 0
    assert picture.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_costmap_refuses_a_bad_profile_in_one_line(maps, tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("costs: {car: 300}\nground: [road]\n")
    assert map_tool.main(["costmap", str(maps["whole"]), "--out", str(tmp_path / "g.npz"), "--profile",
                          str(bad), "--quiet"]) == 2
    assert one_line_error(capsys) == f"map_tool: error: {bad}: cost of 'car' must be a number from 0 to 100, got 300"
    assert not (tmp_path / "g.npz").exists()


def test_evaluate_scores_the_costmap_against_the_ground_truth(tmp_path, capsys):
    """--costmap-report: the JSON has the map's and the baseline's group scores and planning
    check, their picture is written, and the scores are those of costmap_eval on the saved map."""
    from convbki_core.costmap.profile import load_profile
    from convbki_core.measures.costmap_eval import GroundTruthVoxels, grids_for, score_grid
    from convbki_core.paths import traversability_profile

    write_drive(tmp_path / "data", "08", frames=4)
    report, saved = tmp_path / "costmap.json", tmp_path / "final.npz"
    assert evaluate.main(["--dataset", str(tmp_path / "data"), "--sequence", "08", "--report", str(tmp_path / "r.json"),
                          "--costmap-report", str(report), "--save-map", str(saved), "--quiet", *SMALL_WINDOW]) == 0
    assert "costmap (car) against the ground truth's" in capsys.readouterr().out
    written = json.loads(report.read_text())
    assert written["profile"] == "car" and set(written) >= {"map", "baseline", "input"}
    assert set(written["map"]["planning"]) >= {"pairs", "crossing_truth_lethal", "length_ratio_median"}
    assert report.with_suffix(".png").read_bytes()[:4] == b"\x89PNG"

    dataset = SemanticKittiSequence(tmp_path / "data", "08")
    truth = GroundTruthVoxels(dataset.label_map.num_classes, 0.2)
    segmentation = GroundTruthVoxels(dataset.label_map.num_classes, 0.2)
    for frame in dataset:
        points = transform(frame.points, frame.pose)
        truth.add(points, frame.ground_truth, frame.moving, frame.pose[:3, 3], BOUNDS)
        segmentation.add(points, np.where(frame.ground_truth > 0, frame.input_labels, 0), frame.moving,
                         frame.pose[:3, 3], BOUNDS)
    metadata, indices, alpha = read_map(saved)
    profile = load_profile(traversability_profile("car"), dataset.label_map.class_names)
    grids = grids_for(indices, alpha, truth, 0.2, metadata["prior"], profile, segmentation)
    scores = score_grid(grids["map"].values, grids["truth"].values)
    assert written["map"]["precision"] == scores.precision and written["map"]["recall"] == scores.recall
    scores = score_grid(grids["input"].values, grids["truth"].values)
    assert written["input"]["precision"] == scores.precision and written["input"]["recall"] == scores.recall
    # The input's grid is the truth's rules applied to the input's labels: where the input is right
    # about every point, it is the truth's grid cell for cell.
    assert not np.array_equal(grids["input"].values, grids["truth"].values)  # the drive's input has errors
    assert np.array_equal(grids_for(indices, alpha, truth, 0.2, metadata["prior"], profile, truth)["input"].values,
                          grids["truth"].values)


def transform(points, pose):
    return points @ pose[:3, :3].T + pose[:3, 3]
