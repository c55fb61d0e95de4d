"""The sim:// frame source: its frames are the renderer's, with per-frame noise, on a frame clock."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest

from selfview.drivers.frame_grabber_v4l2 import FrameGrabber, parse_grabber_url
from selfview.mocks.render import render
from selfview.mocks.sim_camera import SimCamera, attach_world
from selfview.mocks.world import SimWorld
from selfview.errors import ConfigError, DeviceTimeout


@pytest.fixture
def world(cell):
    """The reference cell seen by a camera of a quarter the resolution (same view, 16x faster to render):
    pixel coordinates scale by 1/4, so f by 1/4 and kappa [px^-2] by 16."""
    s, cam, sim = 4, cell.camera, cell.simulation
    w, h = cam.width // s, cam.height // s
    small = dataclasses.replace(
        cell,
        camera=dataclasses.replace(cam, width=w, height=h, principal_point=((w - 1) / 2, (h - 1) / 2)),
        simulation=dataclasses.replace(sim, true_f=sim.true_f / s, true_kappa=sim.true_kappa * s * s),
    )
    world = SimWorld(small, seed=11)
    world.park()
    return world


@pytest.fixture
def full_world(cell):
    world = SimWorld(cell, seed=11)
    world.park()
    return world


def test_exact_frames_are_the_renderers_bit_for_bit(world):
    cam = SimCamera(world, fps=100, seed=5, exact=True)
    cam.open()
    img, _ = cam.read(1.0)
    assert np.array_equal(img, render(world, seed=cam.last_seed).image)


def test_fast_frames_add_fresh_noise_to_one_cached_render(world):
    cam = SimCamera(world, fps=100, seed=5)
    cam.open()
    a, ta = cam.read(1.0)
    seed_a = cam.last_seed
    b, tb = cam.read(1.0)
    assert cam.renders == 1  # nothing changed in the world: rendered once
    assert not np.array_equal(a, b) and seed_a != cam.last_seed  # but every frame has its own noise
    ref = render(world, seed=seed_a)
    assert np.abs(a.astype(int) - ref.image).max() <= 1  # the renderer's noise, rounded once more
    clean = cam.last_render.image.astype(float)
    interior = (clean > 10) & (clean < 245)  # away from clipping
    resid = (a.astype(float) - clean)[interior]
    sigma = world.cell.simulation.image.noise_gray
    assert abs(resid.mean()) < 0.05 and resid.std() == pytest.approx(np.hypot(sigma, 12**-0.5), rel=0.05)
    assert tb > ta


def test_noise_off_and_settings_pass_through(world):
    cam = SimCamera(world, fps=100, noise=False, blur_px=0.0, gain=0.5)
    cam.open()
    img, _ = cam.read(1.0)
    assert np.array_equal(img, render(world, noise=False, blur_px=0.0, gain=0.5).image)


def test_a_world_change_is_rendered_and_seeds_repeat(world, cell):
    cam = SimCamera(world, fps=100, seed=2)
    cam.open()
    open_img, _ = cam.read(1.0)
    world.set_jaw(cell.gripper.states["closed"], "closed")
    closed_img, _ = cam.read(1.0)
    assert cam.renders == 2
    changed = np.abs(open_img.astype(int) - closed_img) > 30  # far beyond the noise: the fingers moved
    assert changed.sum() > 0.05 * changed.size
    again = SimCamera(world, fps=100, seed=2)
    again.open()
    again.read(1.0)
    assert again.last_seed != cam.last_seed  # a new camera with the same seed starts the same sequence ...
    again.read(1.0)
    assert again.last_seed == cam.last_seed  # ... so its second frame has the second frame's noise


def test_frame_clock(world):
    now = [100.0]
    slept = []

    def sleep(dt):
        slept.append(dt)
        now[0] += dt

    cam = SimCamera(world, fps=25, noise=False, clock=lambda: now[0], sleep=sleep)
    cam.open()
    _, t0 = cam.read(1.0)
    assert t0 == 100.0
    now[0] += 0.01
    _, t1 = cam.read(1.0)  # waits for the next tick
    assert t1 == pytest.approx(100.04) and slept[-1] == pytest.approx(0.03)
    now[0] += 0.2  # frames nobody read are lost
    _, t2 = cam.read(1.0)
    assert t2 == pytest.approx(100.24) and cam.last_tick == 6
    with pytest.raises(DeviceTimeout):
        cam.read(0.01)  # the next tick is 40 ms away


def test_grabber_reads_sim_through_the_registry(full_world):
    with attach_world(full_world, fps=50) as att:
        with FrameGrabber("sim://?seed=4&noise=0", timeout_s=2.0) as g:
            f0 = g.grab()
            after = time.monotonic() + 0.05
            f1 = g.grab(after=after)
            assert f1.timestamp > after and f1.index > f0.index
            assert f1.image.shape == (576, 768) and f1.image.dtype == np.uint8
            assert np.array_equal(f1.image, f0.image)  # no noise, same world
        (cam,) = att.cameras
        assert cam.fps == 50 and cam.noise is False and cam.renders == 1
    with pytest.raises(ConfigError, match="attach_world"):
        FrameGrabber("sim://").connect()  # detached


@pytest.mark.parametrize("url", ["sim://?fps=fast", "sim://?noise=yes", "sim://?colour=1", "sim://cam0"])
def test_bad_sim_urls(world, url):
    with pytest.raises(ConfigError):
        SimCamera.from_url(world, parse_grabber_url(url))


def test_the_picture_follows_the_gripper_valve(world, cell):
    """Close the jaws through Modbus; a frame exposed after the switch confirmed shows them closed."""
    from selfview.drivers.pneumatic_gripper import PneumaticGripper
    from selfview.mocks.valve_terminal import ValveTerminal

    with ValveTerminal(world, travel_s=0.05) as terminal, PneumaticGripper(terminal.url) as gripper, \
            attach_world(world, fps=100, noise=False), FrameGrabber("sim://") as grabber:
        before = grabber.grab().image
        gripper.close_jaws()
        confirmed = time.monotonic()
        after = grabber.grab(after=confirmed)
        assert world.jaw_gap_mm == cell.gripper.states["closed"]
        expected = render(world, noise=False).image
        assert np.array_equal(after.image, expected) and not np.array_equal(before, expected)
