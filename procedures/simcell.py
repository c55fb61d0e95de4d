"""The simulated cell: every device on its real channel, sharing one simulated world.

The VAL-II controller simulator serves a pseudo-terminal (the driver opens its path as it would
``/dev/ttyS0``), the valve terminal serves Modbus TCP on 127.0.0.1, and ``sim://`` renders the world's
current view. Procedures get the same URLs they would get on a real cell; only the disturbance of the
camera goes straight to the world (on a real cell the operator pulls the cable).
"""

from __future__ import annotations

from dataclasses import dataclass

from selfview.mocks.sim_camera import attach_world
from selfview.mocks.val_controller import ValController
from selfview.mocks.valve_terminal import ValveTerminal
from selfview.mocks.world import SimWorld
from selfview.files.cell import Cell

__all__ = ["SimulatedCell", "CellURLs"]


@dataclass(frozen=True)
class CellURLs:
    """The device URLs a run uses (real or simulated)."""

    robot: str
    gripper: str
    camera: str


class SimulatedCell:
    """Start the simulated devices of ``cell`` (seeded) and stop them on exit.

    ``time_scale`` shortens robot motions (1.0: real time); ``link`` 'pty' or 'tcp' for the robot;
    ``travel_s`` the jaws' travel time; ``taught`` the controller's taught locations (name -> (4, 4) pose;
    default: 'plate', pressing the plate 4 mm into the foam, and 'above' it). ``profile`` the world's
    imperfections (``selfview.mocks.imperfections``: 'ideal' (default), 'realistic', 'paper-like' or an
    ``Imperfections``); ``camera`` the true camera's principal point and aspect
    (``selfview.mocks.world.draw_camera``: 'ideal' the cell's nominal ones, 'realistic' drawn from a real
    camera's ranges). Use as a context manager; ``urls`` names the devices.
    """

    def __init__(self, cell: Cell, *, seed: int = 0, time_scale: float = 0.02, link: str = "pty",
                 travel_s: float = 0.05, taught: dict | None = None, profile=None, camera="ideal"):
        if link not in ("pty", "tcp"):
            from selfview.errors import ConfigError

            raise ConfigError(f"robot link {link!r}: expected 'pty' or 'tcp'")
        self.cell = cell
        self.seed = int(seed)
        self.world = SimWorld(cell, seed=self.seed, imperfections=profile, camera=camera)
        self.time_scale = float(time_scale)
        self.link = link
        self.travel_s = float(travel_s)
        self.taught = taught
        self.robot_sim: ValController | None = None
        self.valve_sim: ValveTerminal | None = None
        self._attachment = None
        self.urls: CellURLs | None = None

    def start(self) -> "SimulatedCell":
        try:
            # a cell ready to work: the operator ran CAL after power-up
            self.robot_sim = ValController(self.world, seed=self.seed, time_scale=self.time_scale,
                                           calibrated=True, taught=self.taught)
            if self.link == "pty":
                robot_url = self.robot_sim.start_pty()
            else:
                robot_url = f"socket://127.0.0.1:{self.robot_sim.start_tcp(0)}"
            self.valve_sim = ValveTerminal(self.world, seed=self.seed, travel_s=self.travel_s,
                                           initial=self.cell.gripper.calibrate_in).start()
            self._attachment = attach_world(self.world, seed=self.seed)
            self.urls = CellURLs(robot=robot_url, gripper=self.valve_sim.url, camera="sim://")
        except BaseException:
            self.stop()
            raise
        return self

    def stop(self) -> None:
        if self._attachment is not None:
            self._attachment.detach()
            self._attachment = None
        if self.valve_sim is not None:
            self.valve_sim.stop()
            self.valve_sim = None
        if self.robot_sim is not None:
            self.robot_sim.stop()
            self.robot_sim = None

    def __enter__(self) -> "SimulatedCell":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
