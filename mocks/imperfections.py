"""The imperfections of a real self-viewing cell, for the simulated world.

The simulated cell of ``SimWorld`` and ``render`` is ideal by default. A real CCIR cell such as the
paper's (Panasonic WV-KS152, 7.5 mm lens, a laser-printed plate, a PUMA 260 with a pneumatic gripper) is
not: ``Imperfections`` lists its imperfections, each with a magnitude (0: off) and the source of its
realistic value beside it, in parts (``PARTS``) switchable alone and named profiles (``PROFILES``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace

import numpy as np

from selfview.files.cell import Cell, GripperSpec, PlateSpec
from selfview.errors import ConfigError

__all__ = [
    "Imperfections",
    "PARTS",
    "PROFILES",
    "RealisedImperfections",
    "resolve",
    "realise",
    "picture_effects",
    "chamfer_cuts",
]


@dataclass(frozen=True)
class Imperfections:
    """Magnitudes of a real cell's imperfections (0 switches a part off). Lengths in mm, pixels in px,
    grey levels 0..255, relative figures as fractions."""

    # --- plate (the paper, section 5: "a laser print ... imprecise positioning of the printer") ---
    #: Relative printing scale error of the sheet (sign drawn per world). Laser printers' paper feed and
    #: toner fusing scale a print by 0.1-0.3 % (e.g. the HP LaserJet 4 service manual
    #: specifies a +-0.2 % image length tolerance). Realistic: 0.2 %.
    plate_scale: float = 0.0
    #: Standard deviation of each disc centre's position error per axis [mm]. At 600 dpi a printer places
    #: toner on a 42 um grid, so a disc's edge is off by up to half a dot: 10-20 um. Realistic: 15 um.
    plate_dot_sd_mm: float = 0.0
    #: Paper not flat: height of a cylindrical bow (cockle) across the sheet [mm]; the sheet lifts towards
    #: the camera in the middle of one direction (random per world). Printed office paper glued or laid on a
    #: board cockles by 0.1-0.5 mm (ISO 187 humidity swings of 50 +- 10 % RH); realistic: 0.2 mm.
    plate_bow_mm: float = 0.0

    # --- fingers ---
    #: Standard deviation of each finger face's position off the cell's nominal one [mm], per face of each
    #: finger (inner, outer, front, back): ISO 2768-1 class m allows +-0.2 mm on 6-30 mm, +-0.3 mm on
    #: 30-120 mm (the jaw gap). Realistic: 0.1 mm (so 95 % within the class's +-0.2 mm).
    finger_dim_sd_mm: float = 0.0
    #: Edge break of the fingers' edges [mm], rendered as a 45 degree chamfer tangent to a round of this
    #: radius: deburred machined parts carry 0.1-0.3 mm (ISO 13715 edge specifications).
    #: Realistic: 0.2 mm.
    finger_edge_radius_mm: float = 0.0

    # --- interlace (CCIR: 2 x 288 lines, the fields 20 ms apart) ---
    #: Standard deviation per image axis of the image motion between the two fields [px]: the odd lines
    #: are sampled 20 ms after the even ones (CCIR Rep. 624, 50 fields/s) while the camera on its light
    #: bracket still vibrates after the robot stopped (a PUMA 260's settling oscillation of some
    #: micrometres at 110 mm, i.e. 0.05-0.3 px). Realistic: 0.15 px.
    field_shift_px: float = 0.0

    # --- grabber (Beyer 1992, "Geometric and radiometric analysis of a CCD-camera based photogrammetric
    # close-range system", ETH Zurich: line jitter and PLL line-sync errors of tenths of a pixel) ---
    #: Standard deviation of each line's horizontal shift (line jitter of the PLL pixel clock) [px].
    #: Realistic: 0.1 px.
    line_jitter_px: float = 0.0
    #: Horizontal shift growing linearly from the top line to the bottom one (PLL shear) [px, total]; the
    #: sign is drawn per world (one grabber). Realistic: 0.3 px.
    pll_shear_px: float = 0.0
    #: Analogue video noise added to the sensor noise, correlated along the line by the 5 MHz video
    #: bandwidth sampled at 14.75 MHz (sigma 1 px along u) [grey levels, sd]. The WV-KS152's datasheet
    #: gives S/N 46 dB: 1.3 grey levels of 255; realistic: 1.3.
    analog_noise_gray: float = 0.0

    # --- light ---
    #: Relative illumination change across the picture's width (a lamp to one side). Realistic: 0.10.
    light_gradient: float = 0.0
    #: Relative light loss at the picture's corners: the cos^4 law for a 7.5 mm lens on a 1/2" sensor
    #: (half-diagonal 28 deg) loses 39 %; lenses compensate part of it. Realistic: 0.25.
    vignetting: float = 0.0
    #: Standard deviation of the relative brightness between frames (fluorescent lamps on 50 Hz mains,
    #: beating with the camera's shutter). Realistic: 0.02.
    flicker: float = 0.0

    # --- disturbance ---
    #: Standard deviation per axis of the pivot of a disturbance about the configured one [mm]: a camera
    #: on a clamp and a cable turns about no fixed axis (the paper, section 4 and 5). Realistic: 20 mm.
    pivot_sd_mm: float = 0.0
    #: Standard deviation per axis of a translation (slip) of the camera on its mount added to the
    #: rotation [mm] (the paper's Table 2 series: "loosened the camera attachment"). Realistic: 0.2 mm.
    slip_sd_mm: float = 0.0
    #: Standard deviation of a roll of the camera about its optical axis per mm^2 of the disturbance's TCP
    #: shift [deg/mm^2]: an attachment twists as it tilts, little under a small pull and much once it gives
    #: way. The paper's Table 2 (4P-U's c_z 0.21 mm, three times 4P-R's 0.07, after a 4.5 mm shift) needs
    #: a roll of about 3.5 deg (4P-U's linearisation error about the optical axis, bench/update_limit.py:
    #: 0.14 mm at 2.8 deg, 0.31 at 4.3 deg; about the tilt axis it stays under 0.02 mm), while its Table 1
    #: (4P-U's c_z 0.04 after 1.5 mm) allows under 1 deg: 0.17 deg/mm^2 gives 3.4 and 0.4 deg. Not in
    #: ``realistic`` (no measurement of a mount); ``paper-like`` takes it from the paper.
    roll_deg_per_mm2: float = 0.0

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v >= 0):
                raise ConfigError(f"imperfection {f.name}: expected a magnitude >= 0, got {v!r}")

    @property
    def ideal(self) -> bool:
        return all(getattr(self, f.name) == 0 for f in fields(self))

    @property
    def per_frame(self) -> bool:
        """Whether every frame differs beyond the sensor noise (interlace, line jitter, analogue noise, flicker)."""
        return bool(self.field_shift_px or self.line_jitter_px or self.analog_noise_gray or self.flicker)

    def only(self, part: str) -> "Imperfections":
        """This profile with every part but ``part`` (a key of ``PARTS``) switched off."""
        if part not in PARTS:
            raise ConfigError(f"imperfection part {part!r}: expected one of {', '.join(PARTS)}")
        return Imperfections(**{k: getattr(self, k) for k in PARTS[part]})

    def without(self, part: str) -> "Imperfections":
        """This profile with ``part`` switched off."""
        if part not in PARTS:
            raise ConfigError(f"imperfection part {part!r}: expected one of {', '.join(PARTS)}")
        return replace(self, **{k: 0.0 for k in PARTS[part]})

    def scaled(self, **factors: float) -> "Imperfections":
        """Multiply the magnitudes of parts: ``scaled(fingers=2)``."""
        out = self
        for part, k in factors.items():
            out = replace(out, **{f: getattr(self, f) * float(k) for f in PARTS[part]})
        return out

    def as_dict(self) -> dict:
        return asdict(self)


#: Each part and its fields: ``plate`` printing scale error, random disc position errors, the sheet not
#: flat; ``fingers`` dimensions off nominal, rounded (chamfered) edges; ``interlace`` the two CCIR fields
#: taken 20 ms apart while the camera vibrates; ``grabber`` line jitter and PLL shear of the frame
#: grabber, analogue noise; ``light`` illumination gradient, vignetting, flicker between frames;
#: ``disturbance`` the mount's motion not a pure rotation about the configured pivot.
PARTS: dict[str, tuple[str, ...]] = {
    "plate": ("plate_scale", "plate_dot_sd_mm", "plate_bow_mm"),
    "fingers": ("finger_dim_sd_mm", "finger_edge_radius_mm"),
    "interlace": ("field_shift_px",),
    "grabber": ("line_jitter_px", "pll_shear_px", "analog_noise_gray"),
    "light": ("light_gradient", "vignetting", "flicker"),
    "disturbance": ("pivot_sd_mm", "slip_sd_mm", "roll_deg_per_mm2"),
}

REALISTIC = Imperfections(
    plate_scale=0.002, plate_dot_sd_mm=0.015, plate_bow_mm=0.2,
    finger_dim_sd_mm=0.1, finger_edge_radius_mm=0.2,
    field_shift_px=0.15,
    line_jitter_px=0.1, pll_shear_px=0.3, analog_noise_gray=1.3,
    light_gradient=0.10, vignetting=0.25, flicker=0.02,
    pivot_sd_mm=20.0, slip_sd_mm=0.2,
)

#: Named profiles (``--profile``): ``ideal`` everything off (every exact test uses it); ``realistic``
#: every part at the realistic magnitude of its source; ``paper-like`` the combination of realistic
#: magnitudes under which the simulated Tables 1 and 2 come nearest the paper's (found with
#: ``bench/error_budget.py``).
PROFILES: dict[str, Imperfections] = {
    "ideal": Imperfections(),
    "realistic": REALISTIC,
    #: the realistic cell with the fingers at the coarse end of their tolerances (sd 0.3 mm: ISO 2768-1
    #: class c allows +-0.5 mm on 6-30 mm; worn jaws) and the attachment's roll the paper's Table 2
    #: implies (bench/error_budget.py, docs/RESULTS.md). A sheet bowed by 0.3 mm or edges broken by 0.3 mm
    #: raise Table 2's 4P-R c_z (the reference's) far above the paper's 0.07 mm: they stay realistic.
    "paper-like": replace(REALISTIC, finger_dim_sd_mm=0.3, roll_deg_per_mm2=0.17),
}


def resolve(imperfections) -> Imperfections:
    """None or 'ideal' -> the ideal cell; a profile name -> that profile; an ``Imperfections`` as it is."""
    if imperfections is None:
        return PROFILES["ideal"]
    if isinstance(imperfections, Imperfections):
        return imperfections
    if isinstance(imperfections, str):
        try:
            return PROFILES[imperfections]
        except KeyError:
            raise ConfigError(
                f"simulation profile {imperfections!r}: expected one of {', '.join(PROFILES)}"
            ) from None
    raise ConfigError(f"imperfections: expected a profile name or an Imperfections, got {type(imperfections).__name__}")


# --- what is drawn per world ------------------------------------------------------------------------
class RealisedImperfections:
    """One world's draw of its imperfections: the printed plate, the real fingers, the disturbances' rng.

    Drawn from a generator of its own, seeded from the world's seed, so that switching a part on changes
    nothing else in the world (the same mount, parking offsets and disturbances as the ideal cell). What
    changes per picture (interlace, line jitter, analogue noise, flicker) is drawn from the render's seed.

    ``disc_centres_W`` (rows*cols, 3): the printed disc centres in W [mm] (z < 0: lifted towards the
    camera); ``finger_faces`` (2, 4): per finger the offsets [mm] of its inner, outer, front (-y) and back
    (+y) faces, positive outwards; ``shear_sign`` of the grabber's PLL shear.
    """

    def __init__(self, imp: Imperfections, cell: Cell, seed: int):
        self.imp = imp
        rng = np.random.default_rng([int(seed), 0x1A7E])
        plate: PlateSpec = cell.plate
        nominal = plate.disc_centres_W()
        self.scale = float(imp.plate_scale * rng.choice([-1.0, 1.0]))
        centres = nominal * (1.0 + self.scale)
        centres[:, :2] += rng.normal(0.0, 1.0, (len(centres), 2)) * imp.plate_dot_sd_mm
        # the bow: a cylinder along a random direction, highest on the sheet's middle line
        a = rng.uniform(0, np.pi)
        across = centres[:, 0] * np.cos(a) + centres[:, 1] * np.sin(a)
        half = 0.5 * float(min(plate.size))
        centres[:, 2] = -imp.plate_bow_mm * np.clip(1.0 - (across / half) ** 2, 0.0, 1.0)
        self.disc_centres_W = centres
        self.bow_direction_rad = float(a)
        faces = np.clip(rng.normal(0.0, 1.0, (2, 4)), -2.5, 2.5) * imp.finger_dim_sd_mm
        self.finger_faces = faces
        self.shear_sign = float(rng.choice([-1.0, 1.0]))
        self.rng = rng  # the disturbances' draws

    # fingers
    def finger_boxes_G(self, gripper: GripperSpec, gap: float) -> list[tuple[np.ndarray, np.ndarray]]:
        """The real fingers' boxes in G [mm] (lo, hi) for a nominal jaw gap."""
        if not self.imp.finger_dim_sd_mm:
            return gripper.finger_boxes_G(gap)
        out = []
        for k, (lo, hi) in enumerate(gripper.finger_boxes_G(gap)):
            inner, outer, front, back = self.finger_faces[k]
            lo, hi = lo.copy(), hi.copy()
            if k == 0:  # finger A at +x: inner face lo x, outer face hi x
                lo[0] -= inner
                hi[0] += outer
            else:  # finger B at -x: inner face hi x, outer face lo x
                hi[0] += inner
                lo[0] -= outer
            lo[1] -= front
            hi[1] += back
            out.append((lo, hi))
        return out

    def points_G(self, gripper: GripperSpec, gap: float) -> np.ndarray:
        """(6, 3) the real fingertip corners in G [mm] (POINT_NAMES order) for a nominal jaw gap."""
        if not self.imp.finger_dim_sd_mm:
            return gripper.points_G(gap=gap)
        (alo, ahi), (blo, bhi) = self.finger_boxes_G(gripper, gap)
        return np.array([
            [alo[0], alo[1], 0.0], [alo[0], ahi[1], 0.0],
            [bhi[0], blo[1], 0.0], [bhi[0], bhi[1], 0.0],
            [ahi[0], alo[1], 0.0], [blo[0], blo[1], 0.0],
        ])

    # disturbance
    def disturbance(self, pivot_C) -> tuple[np.ndarray, np.ndarray, float]:
        """The pivot of one disturbance (3,) and the camera's slip (3,) [mm, camera frame], and its roll
        about the optical axis per mm^2 of TCP shift [deg/mm^2]."""
        pivot = np.asarray(pivot_C, float) + self.rng.normal(0.0, 1.0, 3) * self.imp.pivot_sd_mm
        slip = self.rng.normal(0.0, 1.0, 3) * self.imp.slip_sd_mm
        roll_per_mm2 = float(self.rng.normal()) * self.imp.roll_deg_per_mm2
        return pivot, slip, roll_per_mm2


def realise(imp: Imperfections, cell: Cell, seed: int) -> RealisedImperfections:
    return RealisedImperfections(imp, cell, seed)


# --- rendering helpers --------------------------------------------------------------------------------
def chamfer_cuts(lo, hi, radius: float) -> list[tuple[np.ndarray, float, int]]:
    """Half-spaces n . p <= c (in the box's frame) cutting 45 degree chamfers on the edges of a finger's
    tip face (z = hi z) and on its four long edges (along z), tangent to a round of ``radius``: the plane
    lies (sqrt 2 - 1) r from the sharp edge along the bisector. Returns [(n (3,), c, face)], ``face``
    the box face (0..5: -x, +x, -y, +y, -z, +z) whose label the chamfer takes."""
    if radius <= 0:
        return []
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    inset = (np.sqrt(2.0) - 1.0) * radius
    cuts = []
    # the bisector normal of the edge between face a (axis i, side si) and face b (axis j, side sj)
    for (i, si), (j, sj) in (
        [((0, s), (1, t)) for s in (-1, 1) for t in (-1, 1)]  # long edges
        + [((0, s), (2, 1)) for s in (-1, 1)] + [((1, s), (2, 1)) for s in (-1, 1)]  # tip edges
    ):
        n = np.zeros(3)
        n[i], n[j] = si, sj
        n /= np.sqrt(2.0)
        edge = np.zeros(3)
        edge[i] = hi[i] if si > 0 else lo[i]
        edge[j] = hi[j] if sj > 0 else lo[j]
        c = float(n @ edge) - inset
        face = 2 * i + (si > 0) if i != 2 else 5
        cuts.append((n, c, int(face)))
    return cuts


#: Reflected border [px] around the picture for the band-limited shifts of ``_shifted``.
_SHIFT_PAD = 16


def _shifted(value: np.ndarray, axis: int, shift) -> np.ndarray:
    """``value`` (H, W) moved along ``axis`` (1: u, each line by its own ``shift[v]``; 0: v, by one
    ``shift``) by a band-limited (Fourier) shift: a grabber samples the analogue line, band-limited to
    5 MHz against its 14.75 MHz pixel clock, at moved instants, so sinc interpolation is the physics, and
    it moves a disc's centroid by exactly the shift. (OpenCV's remap quantises sub-pixel positions to
    1/32 px and its cubic kernel moves a centroid by up to 0.025 px more or less than asked: a 0.3 px
    shear came out 1.2-1.3 times as strong, a 0.01 px shift not at all.) Borders reflected."""
    pad = _SHIFT_PAD
    p = np.pad(value, pad, mode="reflect")
    n = p.shape[axis]
    freq = np.fft.rfftfreq(n)
    F = np.fft.rfft(p, axis=axis)
    if axis == 1:
        s = np.pad(np.asarray(shift, float), pad, mode="edge")
        F *= np.exp(-2j * np.pi * s[:, None] * freq[None, :])
    else:
        F *= np.exp(-2j * np.pi * float(shift) * freq)[:, None]
    return np.fft.irfft(F, n=n, axis=axis)[pad:-pad, pad:-pad]


def picture_effects(value: np.ndarray, imp: Imperfections, real: RealisedImperfections | None, seed,
                    margin: int, width: int, height: int, noise: bool = True) -> tuple[np.ndarray, dict]:
    """Apply the grabber's and the light's imperfections to the optical picture ``value`` (Hm, Wm) float,
    pixel (u, v) at [v + margin, u + margin], after the optics' blur and before the sensor noise and
    quantisation. Returns the new array (the same one when nothing is switched on) and what was drawn
    (JSON-ready: ``flicker_gain``, ``field_shift_px`` (du, dv) of the odd lines, ``line_shift_px`` per
    picture line (jitter and shear), ``analog_noise_gray``).

    - light: ``value *= (1 + g x)(1 - vig r^2) * (1 + flicker N)``, x in -1/2..1/2 across the width,
      r = 1 at the picture's corners;
    - interlace: the odd lines sample the optical picture moved by the field shift (du, dv);
    - grabber: each line moved along u by its jitter plus the PLL shear (linear in v), then the analogue
      noise (correlated along the line) added.
    Shifts are how far the picture's content moves (+u: right, +v: down). ``noise=False`` leaves out
    the analogue noise. Draws from ``numpy.random.default_rng([seed, 0xF1E1D])`` (None: fresh draws).
    """
    light = imp.light_gradient or imp.vignetting or imp.flicker
    geometric = imp.field_shift_px or imp.line_jitter_px or imp.pll_shear_px
    analog = imp.analog_noise_gray if noise else 0.0
    if not (light or geometric or analog):
        return value, {}
    drawn: dict = {}
    rng = np.random.default_rng(None if seed is None else [int(seed), 0xF1E1D])
    Hm, Wm = value.shape
    m = int(margin)
    vv, uu = np.mgrid[-m : Hm - m, -m : Wm - m].astype(np.float64)
    if light:
        xn = (uu - (width - 1) / 2) / width
        yn = (vv - (height - 1) / 2) / height
        r2 = (xn**2 + yn**2) / 0.5
        gain = 1.0 + imp.flicker * float(rng.normal())
        value = value * ((1.0 + imp.light_gradient * xn) * (1.0 - imp.vignetting * r2) * gain)
        drawn["flicker_gain"] = gain
    if geometric:
        field = rng.normal(0.0, 1.0, 2) * imp.field_shift_px
        jitter = rng.normal(0.0, 1.0, Hm) * imp.line_jitter_px
        shear = (real.shear_sign if real is not None else 1.0) * imp.pll_shear_px
        rows = np.arange(Hm) - m
        du = jitter + shear * (rows - (height - 1) / 2) / height
        odd = (rows % 2) == 1
        drawn["field_shift_px"] = field.tolist()
        drawn["line_shift_px"] = du[m : m + height].tolist()
        # the odd field: the picture moved by the field shift; then every line moved along u by its own
        # shift (the field's du added on the odd lines)
        if field[1]:
            value = np.where(odd[:, None], _shifted(value, 0, field[1]), value)
        value = _shifted(value, 1, du + np.where(odd, field[0], 0.0))
    if analog:
        import cv2

        white = rng.normal(0.0, 1.0, value.shape)
        k = cv2.getGaussianKernel(9, 1.0, cv2.CV_64F)
        corr = cv2.sepFilter2D(white, cv2.CV_64F, k, np.ones((1, 1)), borderType=cv2.BORDER_REFLECT)
        corr *= analog / np.sqrt(float(np.sum(k**2)))
        value = value + corr
        drawn["analog_noise_gray"] = float(analog)
    return value, drawn
