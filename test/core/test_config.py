"""``MapperConfig``: one set of defaults, settings by their flat names, the paper's set-up, and
the node's parameters file read into it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from convbki_core import ConvBKIMapper
from convbki_core.config import DEFAULTS, PAPER_BOUNDS, MapperConfig
from convbki_core.io.labels import load_label_map

REPO = Path(__file__).resolve().parents[2]
SMALL = ((-2.0, -2.0, -1.0), (2.0, 2.0, 1.0))


def test_the_defaults_are_the_products_and_paper_is_plain_convbki():
    label_map = load_label_map("semantic_kitti")
    assert DEFAULTS.window.local_bounds == PAPER_BOUNDS and DEFAULTS.window.prior == 1e-3
    assert DEFAULTS.free_space.enabled and DEFAULTS.free_space.forget_movers
    assert DEFAULTS.movable_classes() == DEFAULTS.forgetting_classes() == label_map.movable_classes
    assert DEFAULTS.ignore_classes() == label_map.ignore_classes
    paper = MapperConfig.paper()
    assert not paper.free_space.enabled and paper.movable_classes() == () and paper.ignore_classes() == (0,)
    assert paper.forgetting_classes() == ()
    # Without free space there are no movers' rules, whatever the classes say; the classes stay movable.
    assert MapperConfig.paper(movable_classes=(1, 2)).forgetting_classes() == ()
    assert MapperConfig.paper(movable_classes=(1, 2)).movable_classes() == (1, 2)
    assert DEFAULTS.replace(forget_movers=False).forgetting_classes() == ()
    assert DEFAULTS.replace(forget_movers=False).movable_classes() == label_map.movable_classes
    assert MapperConfig.paper(free_space=True, movable_classes=(1, 2)).forgetting_classes() == (1, 2)
    # The ground, which free space leaves: the label map's in the product, none in the paper's set-up.
    assert DEFAULTS.ground_classes() == label_map.ground_classes == (9, 10, 11, 12, 17)
    assert paper.ground_classes() == () and MapperConfig.paper(ground_classes=[9]).ground_classes() == (9,)
    with pytest.raises(ValueError, match=r"ground classes must be classes 1\.\.19"):
        ConvBKIMapper(DEFAULTS.replace(device="cpu", local_bounds=SMALL, ground_classes=(0, 9)))


def test_replace_changes_settings_by_their_flat_names_and_refuses_unknown_ones():
    config = DEFAULTS.replace(prior=0.01, device="cpu", free_space=False, local_bounds=[[-1, -1, -1], [1, 1, 1]])
    assert (config.window.prior, config.compute.device, config.free_space.enabled) == (0.01, "cpu", False)
    assert config.window.local_bounds == ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    assert DEFAULTS.window.prior == 1e-3 and DEFAULTS.free_space.enabled  # frozen: the defaults stay
    assert config.flat()["prior"] == 0.01 and set(config.flat()) >= {"free_space", "update_path", "kernel_file"}
    with pytest.raises(TypeError, match="no setting 'max_concentraton'"):
        DEFAULTS.replace(max_concentraton=10.0)


def test_the_node_parameters_file_reads_as_its_settings(tmp_path):
    assert MapperConfig.from_params_file(REPO / "config" / "mapper.yaml") == DEFAULTS
    params = tmp_path / "robot.yaml"
    params.write_text("convbki_mapper:\n  ros__parameters:\n    prior: 0.005\n    free_space: false\n"
                      "    local_bounds: [-10.0, -10.0, -2.0, 10.0, 10.0, 2.0]\n    map_frame: world\n"
                      "    publish_period: 2.0\n")
    config = MapperConfig.from_params_file(params)
    assert config.window.prior == 0.005 and not config.free_space.enabled and config.frame_id == "world"
    assert config.window.local_bounds == ((-10.0, -10.0, -2.0), (10.0, 10.0, 2.0))
    assert config.replace(prior=1e-3, free_space=True, local_bounds=PAPER_BOUNDS, frame_id="map") == DEFAULTS


def test_a_mapper_is_what_its_configuration_says():
    mapper = ConvBKIMapper(DEFAULTS.replace(device="cpu", local_bounds=SMALL, max_concentration=50.0))
    assert mapper.free_space and mapper.forgetting is not None and mapper.max_concentration == 50.0
    assert mapper.update.name == "fast" and mapper.free is not None and mapper.config.window.local_bounds == SMALL
    plain = ConvBKIMapper(MapperConfig.paper(device="cpu", local_bounds=SMALL, update_path="dense"))
    assert not plain.free_space and plain.forgetting is None and plain.free is None and plain.update.name == "dense"
    points = np.random.default_rng(0).uniform(-1.5, 1.5, (500, 3))
    labels = np.random.default_rng(1).integers(1, 20, 500)
    assert plain.integrate(points, labels, np.eye(4)).new_voxels > 0
    with pytest.raises(ValueError, match="update_path"):
        ConvBKIMapper(MapperConfig.paper(device="cpu", local_bounds=SMALL, update_path="sparse"))
    with pytest.raises(ValueError, match="prior must be positive"):
        ConvBKIMapper(MapperConfig.paper(device="cpu", local_bounds=SMALL, prior=0.0))
