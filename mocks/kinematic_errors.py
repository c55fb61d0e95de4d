"""A worn PUMA 260: true link lengths and joint zeros off the published ones, and noisy joint encoders.

Two figures of an arm, apart: its ABSOLUTE accuracy (where it lands against where its published kinematics say:
the link lengths and joint zeros, what a classical hand/eye calibration inherits through the reported poses) and
its REPEATABILITY (how closely it lands on one command again and again: here the encoder noise), which has a data
sheet value, ISO 9283 RP (``iso9283``). ``PROFILES`` names the arms the studies use, each with its RP.

The controller computes poses with the NOMINAL geometry (``selfview.mocks.puma260.Puma260Geometry()``): that is
all a real controller knows. The arm itself follows a TRUE geometry whose six link lengths and six joint
zeros differ from the nominal by ``KinematicErrors.link_mm`` and ``joint_offset_deg`` times a fixed
seeded pattern in [-1, 1] (so one seed at growing error levels is the same robot wearing further), and
each joint's encoder reads its true angle with a fresh Gaussian error of ``encoder_sd_deg``. The arm is
at ``true.fk(q_true)``; the controller believes it is at ``nominal.fk(q_read)`` with
``q_read = q_true + encoder error``. That difference is what classical hand/eye calibration inherits.

``PerturbedPuma260`` is the arm; ``PerturbedValController`` serves it on the VAL-II simulator's real
channel (WHERE and motion planning nominal, the simulated world moved by the true arm).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from selfview.mocks.puma260 import ArmConfig, Puma260, Puma260Geometry
from selfview.mocks.val_controller import ValController
from selfview.errors import ConfigError

__all__ = ["KinematicErrors", "WORN_PUMA", "WORN_NOISY_PUMA", "RATED_RP_MM", "ArmProfile", "PROFILES", "arm_profile",
           "iso9283", "LINKS", "Station", "PerturbedPuma260", "PerturbedValController"]

#: The link lengths of ``Puma260Geometry`` that a worn or mis-built arm gets wrong.
LINKS: tuple[str, ...] = ("shoulder_mm", "upper_arm_mm", "lateral_mm", "elbow_drop_mm", "forearm_mm", "flange_mm")


@dataclass(frozen=True)
class KinematicErrors:
    """How far a simulated arm is from its nominal kinematics.

    ``link_mm``: each link length is off by up to this [mm]; ``joint_offset_deg``: each joint's zero by
    up to this [deg] (both times a seeded pattern in [-1, 1]); ``encoder_sd_deg``: standard deviation of
    each joint reading [deg], drawn afresh at every reading.
    """

    link_mm: float = 0.0
    joint_offset_deg: float = 0.0
    encoder_sd_deg: float = 0.0

    def __post_init__(self):
        for nm in ("link_mm", "joint_offset_deg", "encoder_sd_deg"):
            v = getattr(self, nm)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v >= 0):
                raise ConfigError(f"KinematicErrors.{nm}: expected a finite number >= 0, got {v!r}")

    def scaled(self, level: float) -> "KinematicErrors":
        """These errors times ``level`` (0: a perfect arm, 1: these bounds)."""
        if not (np.isfinite(level) and level >= 0):
            raise ConfigError(f"kinematic error level: expected a finite number >= 0, got {level!r}")
        return KinematicErrors(self.link_mm * level, self.joint_offset_deg * level, self.encoder_sd_deg * level)

    def to_dict(self) -> dict:
        return {"link_mm": self.link_mm, "joint_offset_deg": self.joint_offset_deg, "encoder_sd_deg": self.encoder_sd_deg}


#: The PUMA 260's rated repeatability, +-0.05 mm (Unimation's data sheet): ISO 9283 RP [mm].
RATED_RP_MM = 0.05

#: A worn PUMA 260 as a lab has it: link lengths within 1 mm and joint zeros within 0.2 deg of the published
#: kinematics (its absolute accuracy: about 1 mm at the TCP), and a repeatability twice the rated one, RP 0.1 mm.
#: The encoder noise is derived from that RP: the TCP's scatter is linear in the encoder sd (RP 0.603, 0.301,
#: 0.0603 mm at 0.02, 0.01, 0.002 deg; 3000 landings on the positioning study's pose over the block, the same for
#: arms of seeds 1, 2, 3), so RP 0.1 mm needs 0.02 x 0.1 / 0.603 = 0.0033 deg: measured RP 0.0995 mm (3000
#: landings). ``bench/positioning.py``'s ``arm_repeatability`` measures it again (30 landings, ISO 9283's cycles).
WORN_PUMA = KinematicErrors(link_mm=1.0, joint_offset_deg=0.2, encoder_sd_deg=0.0033)

#: The same worn geometry with sloppy encoders, 0.02 deg: RP 0.60 mm (3000 landings), twelve times the rated
#: figure. A sensitivity profile: what an arm that does not repeat does to every calibration.
WORN_NOISY_PUMA = KinematicErrors(link_mm=1.0, joint_offset_deg=0.2, encoder_sd_deg=0.02)


@dataclass(frozen=True)
class ArmProfile:
    """A named simulated arm: ``errors`` its kinematic errors; ``rp_mm`` the ISO 9283 repeatability its encoder
    noise was set from [mm] (None: the noise is a figure of its own, the RP only measured); ``about`` one line."""

    name: str
    errors: KinematicErrors
    rp_mm: float | None
    about: str

    def to_dict(self) -> dict:
        return {"name": self.name, **self.errors.to_dict(), "stated_rp_mm": self.rp_mm, "about": self.about}


#: The arms of the studies, by name (``arm_profile``).
PROFILES: dict[str, ArmProfile] = {p.name: p for p in (
    ArmProfile("none", KinematicErrors(), 0.0, "a perfect arm: the published kinematics, exact encoders"),
    ArmProfile("half-worn", WORN_PUMA.scaled(0.5), RATED_RP_MM,
               "links within 0.5 mm, joint zeros within 0.1 deg, the rated repeatability"),
    ArmProfile("worn", WORN_PUMA, 2 * RATED_RP_MM,
               "a worn PUMA 260: links within 1 mm, joint zeros within 0.2 deg, twice the rated repeatability"),
    ArmProfile("worn-noisy", WORN_NOISY_PUMA, None,
               "the worn geometry with 0.02 deg encoder noise (sensitivity: an arm that does not repeat)"),
)}


def arm_profile(name: str) -> ArmProfile:
    """The arm profile ``name`` of ``PROFILES``; raises ``ConfigError`` naming the known ones otherwise."""
    if not isinstance(name, str) or name not in PROFILES:
        raise ConfigError(f"arm profile {name!r}: expected one of {', '.join(PROFILES)}")
    return PROFILES[name]


def iso9283(landings, command) -> dict:
    """ISO 9283 pose repeatability and accuracy of ``landings`` (n, 3) reached for one ``command`` (3,) [mm]:
    ``rp_mm`` = mean + 3 sd (n - 1) of the landings' distances from their barycentre; ``ap_mm`` the
    barycentre's distance from the command; ``rms_mm`` the RMS distance from the barycentre. Raises
    ``ConfigError`` for fewer than 2 landings or a shape other than (n, 3) and (3,)."""
    x, c = np.asarray(landings, dtype=float), np.asarray(command, dtype=float)
    if x.ndim != 2 or x.shape[1] != 3 or len(x) < 2 or c.shape != (3,):
        raise ConfigError(f"iso9283: expected landings (n >= 2, 3) and a command (3,), got {x.shape} and {c.shape}")
    bary = x.mean(axis=0)
    d = np.linalg.norm(x - bary, axis=1)
    return {"rp_mm": float(d.mean() + 3.0 * d.std(ddof=1)), "ap_mm": float(np.linalg.norm(bary - c)),
            "rms_mm": float(np.sqrt(np.mean(d ** 2))), "landings": len(x)}


@dataclass(frozen=True)
class Station:
    """One robot pose: ``q_read`` (6,) the joints the controller reads [deg]; ``base_H_F_true`` (4, 4)
    where the flange really is; ``base_H_F_nominal`` (4, 4) where the controller's kinematics puts it."""

    q_read: np.ndarray
    base_H_F_true: np.ndarray
    base_H_F_nominal: np.ndarray


class PerturbedPuma260:
    """A PUMA 260 whose true geometry differs from the nominal one of its controller (module docstring).

    ``errors`` the error bounds; ``seed`` fixes the error pattern (which robot) and, unless ``noise_seed``
    is given, the encoder noise; ``noise_seed`` (an int) a stream of encoder draws of its own for the same
    robot (so independent runs of one arm do not repeat each other's landing errors draw for draw);
    ``nominal`` the geometry the controller uses (default the published one); ``config`` the arm
    configuration of the inverse kinematics. ``nominal`` and ``true`` are ``Puma260`` models; ``link_errors_mm`` and
    ``joint_offset_errors_deg`` what was drawn.
    """

    def __init__(self, errors: KinematicErrors = KinematicErrors(), *, seed: int = 0, noise_seed: int | None = None,
                 nominal: Puma260Geometry | None = None, config: ArmConfig | None = None):
        if not isinstance(errors, KinematicErrors):
            raise ConfigError(f"errors: expected a KinematicErrors, got {type(errors).__name__}")
        if noise_seed is not None and (isinstance(noise_seed, bool) or not isinstance(noise_seed, (int, np.integer))
                                       or noise_seed < 0):
            raise ConfigError(f"noise_seed: expected a whole number >= 0 or None, got {noise_seed!r}")
        nominal = nominal or Puma260Geometry()
        config = config or ArmConfig()
        self.errors = errors
        self.seed = int(seed)
        pattern = np.random.default_rng([self.seed, 0]).uniform(-1.0, 1.0, size=12)
        self.link_errors_mm = {nm: float(errors.link_mm * u) for nm, u in zip(LINKS, pattern[:6])}
        self.joint_offset_errors_deg = tuple(float(errors.joint_offset_deg * u) for u in pattern[6:])
        changes = {nm: getattr(nominal, nm) + e for nm, e in self.link_errors_mm.items()}
        changes["joint_offsets_deg"] = tuple(
            o + e for o, e in zip(nominal.joint_offsets_deg, self.joint_offset_errors_deg)
        )
        self.nominal = Puma260(nominal, config)
        self.true = Puma260(nominal.with_errors(**changes), config)
        self.noise_seed = None if noise_seed is None else int(noise_seed)
        # a stream of its own: [seed, 2, n] (a trailing 0 seeds as [seed, 2]), never the robot's own [seed, 1]
        self._noise = np.random.default_rng([self.seed, 1] if noise_seed is None else [self.seed, 2, self.noise_seed])

    def encoder_error_deg(self) -> np.ndarray:
        """(6,) one fresh draw of the joint encoders' errors [deg]."""
        return self._noise.normal(0.0, self.errors.encoder_sd_deg, size=6) if self.errors.encoder_sd_deg > 0 else np.zeros(6)

    def move(self, base_H_F_target, q_near_deg=None) -> Station:
        """Command the flange to ``base_H_F_target`` (4, 4): the controller solves its nominal inverse
        kinematics and servos until the encoders read that; the arm ends where the true geometry puts
        the true joints. Raises ``selfview.mocks.puma260.Unreachable`` for a target the nominal arm cannot reach."""
        q_read = self.nominal.ik(base_H_F_target, q_near_deg)
        q_true = q_read - self.encoder_error_deg()
        return Station(q_read, self.true.fk(q_true), self.nominal.fk(q_read))

    def observe(self, base_H_F_true, q_near_deg=None) -> Station:
        """The arm standing with its flange truly at ``base_H_F_true`` (4, 4): what the controller reads
        and reports there. Raises ``Unreachable`` for a pose the true arm cannot take."""
        q_true = self.true.ik(base_H_F_true, q_near_deg)
        q_read = q_true + self.encoder_error_deg()
        return Station(q_read, np.asarray(base_H_F_true, dtype=float).copy(), self.nominal.fk(q_read))

    def summary(self) -> dict:
        """The drawn errors, plain numbers (mm, deg)."""
        return {
            **self.errors.to_dict(),
            "seed": self.seed,
            "link_errors_mm": {k: round(v, 6) for k, v in self.link_errors_mm.items()},
            "joint_offset_errors_deg": [round(v, 6) for v in self.joint_offset_errors_deg],
        }


class PerturbedValController(ValController):
    """The VAL-II simulator (same protocol, same channels) in front of a ``PerturbedPuma260``.

    WHERE, the taught locations and motion planning use the arm's nominal kinematics, as a real
    controller does; the simulated world is moved (and checked for contact) by the true geometry, with
    fresh encoder errors at every update. Other arguments as ``ValController``.
    """

    def __init__(self, world=None, *, robot: PerturbedPuma260, **kwargs):
        if not isinstance(robot, PerturbedPuma260):
            raise ConfigError(f"robot: expected a PerturbedPuma260, got {type(robot).__name__}")
        for nm in ("geometry", "config"):
            if nm in kwargs:
                raise ConfigError(f"PerturbedValController: {nm} comes from the robot's nominal model")
        self.robot = robot
        super().__init__(world, geometry=robot.nominal.geometry, config=robot.nominal.config, **kwargs)
        if world is not None:
            world.set_tcp(self._true_tool(self.joints))

    def _true_tool(self, q_read, noise: bool = True) -> np.ndarray:
        q_true = np.asarray(q_read, dtype=float) - (self.robot.encoder_error_deg() if noise else 0.0)
        return self.robot.true.fk(q_true) @ self.tool
