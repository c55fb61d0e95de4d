"""The simulated block to grasp (``selfview.mocks.objects``): where it lies and the world's verdict."""

from __future__ import annotations

import numpy as np
import pytest

from selfview.errors import ConfigError
from selfview.maths.geometry import inv_H
from selfview.measurement.objects import load_object
from selfview.mocks.objects import draw_start, grasp_outcome, place_object
from selfview.mocks.world import SimWorld


@pytest.fixture
def world(cell):
    w = SimWorld(cell, seed=2)
    place_object(w, load_object(), seed=3)
    return w


def test_the_object_lies_on_the_table_in_the_camera_frame(world):
    """The block's top face at its height above the table (base z), and its pose in C the chain through the base."""
    obj = world.object
    assert obj.base_H_O[2, 3] == pytest.approx(obj.spec.block[2])
    assert np.allclose(world.C_H_O, world.C_H_G @ inv_H(world.base_H_G) @ obj.base_H_O, atol=1e-9)
    assert np.allclose(world.truth()["C_H_O"], world.C_H_O)


def test_a_grasp_at_the_grasp_frame_holds_and_far_off_it_does_not(world, cell):
    obj = world.object
    gap = cell.gripper.gap("open")
    world.set_tcp(obj.base_H_O @ obj.spec.O_H_Gstar)
    at = grasp_outcome(world, gap)
    assert at["held"] and at["why"] == "held" and np.allclose(at["offset_mm"], 0.0, atol=1e-9)
    world.set_tcp(obj.base_H_O @ obj.spec.O_H_Gpre)  # the stand-off: the fingertips above the block
    off = grasp_outcome(world, gap)
    assert not off["held"] and "reach only" in off["why"]


@pytest.mark.parametrize("gap", [0.0, -5.0, float("nan"), float("inf"), "56"])
def test_a_bad_jaw_gap_is_refused_by_name(world, gap):
    with pytest.raises(ConfigError, match="gap_open_mm"):
        grasp_outcome(world, gap)


@pytest.mark.parametrize("draws", [0, -1, 2.5, True])
def test_draw_start_refuses_a_bad_number_of_draws(world, draws):
    with pytest.raises(ConfigError, match="draws"):
        draw_start(world, np.random.default_rng(0), draws=draws)


def test_without_an_object_the_world_says_so(cell):
    w = SimWorld(cell, seed=2)
    assert w.C_H_O is None and "C_H_O" not in w.truth()
    with pytest.raises(ConfigError, match="no object"):
        grasp_outcome(w, 56.0)
    with pytest.raises(ConfigError, match="no object"):
        draw_start(w, np.random.default_rng(0))
