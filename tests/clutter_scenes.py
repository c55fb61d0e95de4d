"""Scenes of the simulated cell over real photographs (scikit-image's), beside discs and partly covered,
in both renderers (``selfview.mocks.render`` and the tests' independent ``tests.alt_render``): the
sequences the clutter tests and ``bench/clutter.py`` measure."""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from selfview.maths.geometry import transform_points

#: background family of each photograph
FAMILIES = {
    "gravel": "texture", "grass": "texture", "brick": "texture", "rough-wall": "texture",
    "coffee": "objects", "motorcycle_left": "objects", "astronaut": "objects", "chelsea": "objects",
    "camera": "high-contrast", "coins": "high-contrast", "text": "high-contrast", "page": "high-contrast",
    "rocket": "objects", "hubble_deep_field": "texture", "moon": "texture", "horse": "high-contrast",
}
DEFAULT_PHOTOS = ("gravel", "grass", "brick", "coffee", "motorcycle_left", "astronaut", "camera", "coins")
#: (distance beyond the fingertips [mm], defocus sigma [px]) drawn in turn
SETTINGS = ((15.0, 0.6), (40.0, 1.5), (80.0, 3.0), (25.0, 0.0), (60.0, 2.2))


def photo_dir() -> Path:
    """The ``data`` folder of the installed scikit-image (its photographs), or a clear error."""
    spec = importlib.util.find_spec("skimage")
    if spec is None or not spec.submodule_search_locations:
        raise RuntimeError("the clutter study needs scikit-image's photographs: pip install -e '.[test]'")
    return Path(list(spec.submodule_search_locations)[0]) / "data"


def available_photos() -> list[str]:
    d = photo_dir()
    return [n for n in FAMILIES if (d / f"{n}.png").is_file() or (d / f"{n}.jpg").is_file()]


def load_photo(name: str) -> np.ndarray:
    """A photograph of ``skimage/data`` as a grey uint8 array (read with OpenCV)."""
    d = photo_dir()
    for ext in (".png", ".jpg"):
        p = d / f"{name}{ext}"
        if p.is_file():
            img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise RuntimeError(f"photograph {p.name}: OpenCV could not read it")
            return img
    raise RuntimeError(f"photograph {name!r}: not in scikit-image's data folder ({', '.join(available_photos())})")


def _alt():
    """The tests' independent renderer (``tests.alt_render``)."""
    import tests.alt_render as alt

    return alt


@dataclass
class Frame:
    image: np.ndarray
    C_H_G: np.ndarray  # truth
    corner_uv: np.ndarray  # (6, 2) truth
    corner_visible: np.ndarray


@dataclass
class Sequence:
    """One trial: the undisturbed picture and the disturbed ones, the prediction and the truth."""

    renderer: str
    kind: str
    photo: str
    distance_mm: float
    defocus_px: float
    camera: object
    C_H_G_pred: np.ndarray
    gap: float
    p_G6: np.ndarray
    frames: list  # Frame, the first undisturbed


def _mm_per_px(photo: np.ndarray) -> float:
    """Scale so that the photograph spans about 180 mm (more than the view at these depths)."""
    return 180.0 / max(photo.shape)


def render_frame(renderer: str, world, photo, distance_mm, defocus_px, seed, occluder=None) -> Frame:
    """One picture of ``world`` over ``photo`` (None: the renderer's own plain background)."""
    from selfview.mocks.render import Backdrop, render

    cam = world.camera
    if renderer == "mocks":
        bd = None
        if photo is not None:
            bd = Backdrop(photo, mm_per_px=_mm_per_px(photo), distance_mm=distance_mm, defocus_px=defocus_px,
                          turn_deg=float(seed % 7) * 23.0)
        r = render(world, seed=seed, backdrop=bd)
        return Frame(r.image, world.C_H_G, r.corner_uv, r.corner_visible)
    alt = _alt()
    kw = {"seed": int(seed)}
    if photo is not None:
        from selfview.maths.geometry import rot_z, trans

        # the same plane as the Backdrop's (distance beyond the plate's plane), its own blur model (mm on the table)
        C_H_T = world.C_H_W @ trans(0, 0, distance_mm) @ rot_z(np.radians(float(seed % 7) * 23.0))
        depth = float(C_H_T[2, 3])
        kw.update(table_image=photo, table_mm_per_px=_mm_per_px(photo), C_H_T=C_H_T,
                  table_defocus_mm=defocus_px * depth / cam.f)
    if occluder is not None:
        kw["occluders"] = (occluder,)
    pic = alt.render(cam, world.C_H_G, None, world.jaw_gap_mm, world.cell, **kw)
    return Frame(pic.image, world.C_H_G, pic.corner_uv, pic.corner_visible)


def _cable_across(world, finger: int, rng) -> tuple:
    """A dark cable 2 mm thick, straight across finger ``finger`` some 10..25 mm back from its tip, 6 mm
    in front of it (a box aligned with C: lo, hi, grey)."""
    cell = world.cell
    lo, hi = cell.gripper.finger_boxes_G(world.jaw_gap_mm)[finger]
    pts = transform_points(world.C_H_G, cell.gripper.points_G(gap=world.jaw_gap_mm))
    tip = pts[[0, 1] if finger == 0 else [2, 3]].mean(axis=0)
    back = tip.copy()
    # along the finger in C: from the tip towards the camera side the finger comes from
    axis = world.C_H_G[:3, :3] @ np.array([0.0, 0.0, -1.0])
    back = tip + axis * rng.uniform(10.0, 25.0)
    z = back[2] - 6.0
    c = back * (z / back[2])
    return (np.array([c[0] - 40.0, c[1] - 1.0, z - 1.0]), np.array([c[0] + 40.0, c[1] + 1.0, z + 1.0]), 40.0)


def online_sequence(cell, renderer: str, photo_name: str | None, series: str, seed: int, distance_mm: float,
                    defocus_px: float, steps: int = 4, occluded: bool = False) -> Sequence:
    """A trial of kind ``online`` (or ``occluded``): see the module's docstring."""
    from selfview.mocks.world import SimWorld

    world = SimWorld(cell, seed=seed)
    state = cell.gripper.calibrate_in
    world.set_jaw(cell.gripper.gap(state), state)
    world.park()
    pred = world.C_H_G
    world.unpark()
    photo = None if photo_name is None else load_photo(photo_name)
    rng = np.random.default_rng(seed + 17)
    occ = _cable_across(world, int(seed % 2), rng) if occluded else None
    frames = [render_frame(renderer, world, photo, distance_mm, defocus_px, seed * 10, occ)]
    d = world.disturb(series)
    world.reset_disturbance()
    pivot = cell.simulation.disturbances[series].pivot_C
    for k in range(steps):
        world.disturb_by_angle(d.axis_C, d.angle_deg / steps, pivot_C=pivot, series=series)
        frames.append(render_frame(renderer, world, photo, distance_mm, defocus_px, seed * 10 + 1 + k, occ))
    return Sequence(renderer, "occluded" if occluded else "online", photo_name or "plain", distance_mm, defocus_px,
                    world.camera, pred, world.jaw_gap_mm, world.points_G(), frames)


def disc_picture(cell, renderer: str, seed: int, on: bool) -> tuple[Sequence, float]:
    """A parked picture with a fingertip corner on a disc (``on``) or within 0.2..1.5 mm of a rim: parks
    drawn from ``seed`` until one is. Returns it and the corner's distance from the rim [mm] (negative: on)."""
    from selfview.mocks.world import SimWorld

    plate = cell.plate
    centres = plate.disc_centres_W()[:, :2]
    R = plate.disc_diameter / 2
    state = cell.gripper.calibrate_in
    for k in range(400):
        world = SimWorld(cell, seed=seed * 1000 + k)
        world.set_jaw(cell.gripper.gap(state), state)
        W_H_G = world.park(max_offset_mm=plate.pitch, max_turn_deg=20.0)
        p_W = transform_points(W_H_G, world.points_G())[:, :2]
        d = np.linalg.norm(p_W[:, None, :] - centres[None], axis=2).min(axis=1) - R
        # the tip corners (0..3) of the plate's side
        best = float(d[:4][np.argmin(np.abs(d[:4]))])
        if (on and -R * 0.8 < best < -0.3) or (not on and 0.2 < best < 1.5):
            if renderer == "mocks":
                from selfview.mocks.render import render

                r = render(world, seed=seed)
                fr = Frame(r.image, world.C_H_G, r.corner_uv, r.corner_visible)
            else:
                pic = _alt().render_world(world, seed=int(seed))
                fr = Frame(pic.image, world.C_H_G, pic.corner_uv, pic.corner_visible)
            return Sequence(renderer, "disc", "on disc" if on else "beside disc", 0.0, 0.0, world.camera,
                            cell.mount_guess_C_H_G, world.jaw_gap_mm, world.points_G(), [fr]), best
    raise RuntimeError("no park put a fingertip on/beside a disc")
