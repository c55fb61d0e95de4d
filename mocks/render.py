"""The simulated wrist camera's picture: a ray caster through the true camera model, and its ground truth.

The scene is the plate, the foam block under it, the two fingers and a textured table, in the frames of
``CONVENTIONS.md`` (``_Scene``). Every ray leaves the projection centre through a *distorted* pixel
position, so straight 3-D edges come out slightly curved (eq. 3-4; the correction from distorted to
undistorted is explicit, so no cubic is solved per ray). A pixel's value is the mean of the scene over
its area (``render``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from selfview.mocks.imperfections import chamfer_cuts, picture_effects
from selfview.mocks.world import SimWorld
from selfview.maths.camera import CameraModel, max_undistorted_radius
from selfview.measurement.objects import target_board
from selfview.measurement.plates import board_edges_W, board_ink
from selfview.files.cell import POINT_NAMES, ImageSpec, PlateSpec
from selfview.errors import ConfigError
from selfview.maths.geometry import rot_x, rot_z, trans, transform_points

__all__ = [
    "Backdrop",
    "Lamp",
    "RenderResult",
    "render",
    "disc_image_centroids",
    "FOAM_SIZE_MM",
    "FOAM_GAP_MM",
    "FOAM_THICKNESS_MM",
    "PLATE_THICKNESS_MM",
    "LIGHT_G",
    "LIFTED_W_H_G",
]

#: The foam block: a square slab centred under the plate, its top FOAM_GAP_MM behind the plate plane.
FOAM_SIZE_MM = 200.0
FOAM_GAP_MM = 2.0
FOAM_THICKNESS_MM = 18.0
#: The board the sheet is printed on (z in [0, PLATE_THICKNESS_MM] of W, z into the plate).
PLATE_THICKNESS_MM = 2.0
#: Direction towards the light in G (from the camera's side, above the fingertips, a little from +x):
#: it picks one of the three ``finger`` grey levels for each face of a finger.
LIGHT_G = np.array([0.35, -1.0, -0.8]) / np.linalg.norm([0.35, -1.0, -0.8])
#: A gripper pose off the plate, over the table (in the resting plate's frame W, z into the plate, mm):
#: ``world.set_tcp(world.base_H_plate0 @ LIFTED_W_H_G)`` shows the fingers over the textured table.
LIFTED_W_H_G = trans(130.0, 60.0, -120.0)
#: Grey level of rays that meet nothing (the room above the table).
ROOM_GRAY = 35.0
#: Table texture: extent in B (mm) and resolution (mm per texel); beyond it the texture is mirrored.
_TABLE_X0, _TABLE_Y0, _TABLE_SIZE, _TABLE_RES = -100.0, -450.0, 900.0, 0.5
#: Edge marking: sample spacing along a projected edge (px) and the half-width marked around each sample
#: (more than half the spacing, so that a pixel an edge only clips at a corner is marked too).
_EDGE_STEP_PX = 0.25
_EDGE_HALF_PX = 0.13
_CHUNK = 1 << 18
#: Shadows: the lamp's light is traced at every this many pixels, then in full near a shadow.
_SHADOW_STEP = 4

# Surface labels; finger faces follow from _FINGER0 + 6 * finger + face (faces: -x, +x, -y, +y, -z, +z).
_ROOM, _TABLE, _FOAM_TOP, _FOAM_SIDE, _PAPER, _INK, _PRINT, _BOARD_SIDE, _FINGER0 = range(9)
# an object's block (``selfview.mocks.objects``): its sides and its top face with the printed target
_BLOCK_SIDE, _TARGET = _FINGER0 + 12, _FINGER0 + 13
_N_LABELS = _FINGER0 + 14
#: Bit masks of what shows a label: bit k the box ``_Scene.boxes[k]`` (board, foam, finger A, finger B, the
#: object's block), _PRINT_BIT the printed face of the board; the table and the room have none (the table is
#: always traced).
_PRINT_BIT = 128
_LABEL_BITS = np.array([0, 0, 2, 2, _PRINT_BIT, _PRINT_BIT, _PRINT_BIT, 1] + [4] * 6 + [8] * 6 + [16, 16], np.uint8)
#: The object's target texture: mm per texel.
_TARGET_RES = 0.05
_FACE_NORMALS = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], float)


@dataclass(frozen=True)
class Backdrop:
    """A picture laid as the table behind the fingertips, in place of the plate, its foam and the table.

    ``image`` (h, w) grey levels 0..255 (e.g. a photograph; a colour one is converted), ``mm_per_px`` its
    scale on the table, centred on the plate's origin and mirrored beyond its border. The table is the
    plane ``distance_mm`` beyond the plate's printed plane (where the fingertips stand while parked), along
    W's z (away from the camera), tilted by ``tilt_deg`` about W's x and turned by ``turn_deg`` about its
    normal. ``defocus_px`` the Gaussian sigma [px of the picture] of the table's defocus (the fingers stay
    as sharp as ``blur_px`` makes everything); ``contrast`` scales the grey levels about 128.
    """

    image: np.ndarray
    mm_per_px: float = 0.2
    distance_mm: float = 40.0
    defocus_px: float = 0.0
    tilt_deg: float = 0.0
    turn_deg: float = 0.0
    contrast: float = 1.0

    def check(self) -> None:
        img = np.asarray(self.image)
        if img.ndim not in (2, 3) or min(img.shape[:2]) < 8:
            raise ConfigError(f"backdrop image: expected a grey or colour picture of at least 8x8, got shape {img.shape}")
        for name, lo, hi in (("mm_per_px", 1e-3, 100.0), ("distance_mm", 0.5, 2000.0), ("defocus_px", 0.0, 20.0),
                             ("tilt_deg", -60.0, 60.0), ("turn_deg", -360.0, 360.0), ("contrast", 0.0, 4.0)):
            v = getattr(self, name)
            if not (np.isfinite(v) and lo <= v <= hi):
                raise ConfigError(f"backdrop {name}: expected {lo:g}..{hi:g}, got {v!r}")

    def C_H_T(self, C_H_W: np.ndarray) -> np.ndarray:
        """The table's frame T in the camera frame: its plane z_T = 0, x_T, y_T the picture's axes."""
        return C_H_W @ trans(0.0, 0.0, self.distance_mm) @ rot_x(np.radians(self.tilt_deg)) @ rot_z(np.radians(self.turn_deg))

    def texture(self, depth_mm: float, f_px: float) -> np.ndarray:
        """The picture as float32 grey levels, its defocus applied in its own pixels (the table's depth
        ``depth_mm`` and the focal length ``f_px`` give mm per picture pixel there)."""
        img = np.asarray(self.image)
        if img.ndim == 3:
            img = cv2.cvtColor(np.ascontiguousarray(img[..., :3]).astype(np.uint8), cv2.COLOR_RGB2GRAY)
        tex = (128.0 + self.contrast * (img.astype(np.float32) - 128.0)).astype(np.float32)
        sigma = self.defocus_px * depth_mm / f_px / self.mm_per_px
        if sigma > 0.05:
            tex = cv2.GaussianBlur(tex, (0, 0), sigma, borderType=cv2.BORDER_REFLECT_101)
        return tex


@dataclass(frozen=True)
class Lamp:
    """A lamp that casts shadows: the fingers' own, and those of ``occluders`` (a lamp's arm, a cable).

    ``position_W`` (3,) the lamp's centre in the plate's frame W [mm] (z into the plate: a lamp on the
    camera's side has z < 0); ``radius_mm`` the radius of its round face, turned to W's origin (the
    penumbra's width grows with it); ``ambient`` the share of its light a fully shadowed surface keeps
    (the room's light); ``occluders`` boxes ((lo, hi), ...) in W [mm] besides the fingers; ``samples``
    points on the face traced per pixel (the penumbra's smoothness). The plate, its foam and the table
    take the shadows; the fingers keep their ``LIGHT_G`` shading.
    """

    position_W: tuple = (-150.0, 0.0, -250.0)
    radius_mm: float = 15.0
    ambient: float = 0.45
    occluders: tuple = ()
    samples: int = 16

    def check(self) -> None:
        pos = np.asarray(self.position_W, float)
        if pos.shape != (3,) or not np.all(np.isfinite(pos)) or pos[2] >= 0:
            raise ConfigError(f"lamp position_W: expected (x, y, z) mm with z < 0 (the camera's side of the plate), got {self.position_W!r}")
        for name, lo, hi in (("radius_mm", 0.0, 500.0), ("ambient", 0.0, 1.0)):
            v = getattr(self, name)
            if not (np.isfinite(v) and lo <= v <= hi):
                raise ConfigError(f"lamp {name}: expected {lo:g}..{hi:g}, got {v!r}")
        if isinstance(self.samples, bool) or not isinstance(self.samples, (int, np.integer)) or not 1 <= self.samples <= 256:
            raise ConfigError(f"lamp samples: expected a whole number 1..256, got {self.samples!r}")
        for box in self.occluders:
            if not _is_box(box):
                raise ConfigError(f"lamp occluder: expected ((x0, y0, z0), (x1, y1, z1)) mm with x0 < x1 etc., got {box!r}")

    def points_W(self) -> np.ndarray:
        """(samples, 3) points on the lamp's face [mm, W]: a Fibonacci lattice on the disc facing W's origin."""
        c = np.asarray(self.position_W, float)
        n = -c / np.linalg.norm(c)
        a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(n, a)
        k = np.arange(self.samples) + 0.5
        r = self.radius_mm * np.sqrt(k / self.samples)
        t = k * np.pi * (3.0 - np.sqrt(5.0))
        return c + (r * np.cos(t))[:, None] * a + (r * np.sin(t))[:, None] * b


def _is_box(box) -> bool:
    """Whether ``box`` is ((x0, y0, z0), (x1, y1, z1)) of finite numbers with x0 < x1, y0 < y1, z0 < z1."""
    try:
        lo, hi = (np.asarray(b, float) for b in box)
    except (TypeError, ValueError):
        return False
    return lo.shape == hi.shape == (3,) and bool(np.all(np.isfinite(lo) & np.isfinite(hi) & (lo < hi)))


@dataclass
class RenderResult:
    """A rendered picture and its ground truth.

    ``image`` (H, W) uint8; ``truth`` the JSON object of the render command (f, kappa, principal_point,
    C_H_G, C_H_W as 4x4 lists, ``discs`` [[row, col, u, v, visible], ...], ``corners`` {name: [u, v,
    visible]}, plus the world's and the render's settings); ``disc_uv`` (rows*cols, 2) image of each
    disc's centre point, row-major (NaN where it cannot be projected); ``disc_visible`` (rows*cols,)
    whole disc inside the picture and no part of it covered by a finger; ``corner_uv`` (6, 2) fingertip
    corners in the order of ``POINT_NAMES``; ``corner_visible`` (6,) inside the picture, not occluded.
    """

    image: np.ndarray
    truth: dict
    disc_uv: np.ndarray
    disc_visible: np.ndarray
    corner_uv: np.ndarray
    corner_visible: np.ndarray


# --- scene ----------------------------------------------------------------------------------------
class _Box:
    """An axis-aligned box ``lo``..``hi`` (mm) of frame P, ``C_H_P`` (4, 4), with a label per face."""

    def __init__(self, C_H_P: np.ndarray, lo, hi, face_labels, cuts=()):
        self.cuts = list(cuts)  # chamfers (imperfections.chamfer_cuts): [(n (3,), c, face)], n . p <= c in P
        self.R = np.asarray(C_H_P, float)[:3, :3]
        self.t = np.asarray(C_H_P, float)[:3, 3]
        self.o = -self.R.T @ self.t  # the projection centre in P
        self.lo = np.asarray(lo, float)
        self.hi = np.asarray(hi, float)
        self.face_labels = np.asarray(face_labels, np.int16)
        # vertex i takes hi along axis k where bit k of i is set
        corners_P = np.array([[(self.hi if i >> k & 1 else self.lo)[k] for k in range(3)] for i in range(8)])
        self.vertices_C = transform_points(C_H_P, corners_P)
        # with every vertex in front of the camera the box's image lies in the hull of its vertices' images
        v = self.vertices_C
        if np.all(v[:, 2] > 0):
            xy = v[:, :2] / v[:, 2:3]
            self.bbox = (*(xy.min(axis=0) - 1e-9), *(xy.max(axis=0) + 1e-9))
        else:
            self.bbox = None

    def rays_near(self, x: np.ndarray, y: np.ndarray) -> np.ndarray | None:
        """Indices of the rays (x, y, 1) that may meet the box, or None for all of them."""
        if self.bbox is None:
            return None
        x0, y0, x1, y1 = self.bbox
        inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
        return None if inside.all() else np.flatnonzero(inside)

    def hit(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Slab test of the rays (x, y, 1) in C: (depth z_C of the entry point, inf if missed; face 0..5)."""
        t_near = np.full(x.shape, -np.inf, x.dtype)
        t_far = np.full(x.shape, np.inf, x.dtype)
        face = np.zeros(x.shape, np.int8)
        # Python floats keep single-precision rays in single precision (NEP 50)
        R, lo, hi, o = self.R.tolist(), self.lo.tolist(), self.hi.tolist(), self.o.tolist()
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            for k in range(3):
                d = R[0][k] * x + R[1][k] * y + R[2][k]
                d[d == 0.0] = 1e-30  # a ray parallel to the slab: its entry and exit lie far away
                t1 = (lo[k] - o[k]) / d
                t2 = (hi[k] - o[k]) / d
                t_min = np.minimum(t1, t2)
                later = t_min > t_near
                t_near = np.where(later, t_min, t_near)
                face = np.where(later, 2 * k + (d < 0), face)  # entering through lo (normal -k) when d > 0
                t_far = np.minimum(t_far, np.maximum(t1, t2))
            for n, c, fc in self.cuts:  # the chamfers: half-spaces n . (o + t d) <= c
                nx, ny, nz = (float(self.R[r] @ n) for r in range(3))
                dn = nx * x + ny * y + nz
                tc = (c - float(np.dot(n, o))) / dn
                later = (dn < 0) & (tc > t_near)
                t_near = np.where(later, tc, t_near)
                face = np.where(later, fc, face)
                t_far = np.where(dn > 0, np.minimum(t_far, tc), t_far)
                if float(np.dot(n, o)) > c:
                    t_far = np.where(dn == 0, -np.inf, t_far)
        return np.where((t_near <= t_far) & (t_near > 0), t_near, np.inf), face

    def blocks(self, p: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Whether the box meets the segments from the points ``p`` (N, 3) to ``q`` (3,) of C [mm],
        ends excluded (a surface does not shadow itself); the chamfers are ignored."""
        o = (p - self.t) @ self.R  # in P
        d = (q - self.t) @ self.R - o
        t_near = np.full(len(p), 1e-6)
        t_far = np.full(len(p), 1.0 - 1e-6)
        with np.errstate(divide="ignore", invalid="ignore"):
            for k in range(3):
                dk = np.where(d[:, k] == 0.0, 1e-30, d[:, k])
                t1 = (self.lo[k] - o[:, k]) / dk
                t2 = (self.hi[k] - o[:, k]) / dk
                t_near = np.maximum(t_near, np.minimum(t1, t2))
                t_far = np.minimum(t_far, np.maximum(t1, t2))
        return t_near <= t_far

    def visible_faces(self) -> np.ndarray:
        """(6,) bool: the faces that turn towards the camera."""
        return np.concatenate([[self.o[k] < self.lo[k], self.o[k] > self.hi[k]] for k in range(3)])

    def edges_C(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The box edges (pairs of end points in C, mm) next to at least one face turned to the camera."""
        vis = self.visible_faces()
        out = []
        for i in range(8):
            for k in range(3):
                j = i | (1 << k)
                if j == i:
                    continue
                # the two faces that meet at this edge: the other two axes, on the side the vertex lies
                a, b = [m for m in range(3) if m != k]
                fa = 2 * a + bool(i & (1 << a))
                fb = 2 * b + bool(i & (1 << b))
                if vis[fa] or vis[fb]:
                    out.append((self.vertices_C[i], self.vertices_C[j]))
        return out


class _Plane:
    """The plane z = 0 of frame P, ``C_H_P`` (4, 4): where rays (x, y, 1) of C meet it."""

    def __init__(self, C_H_P: np.ndarray):
        H = np.asarray(C_H_P, float)
        self.R, self.t = H[:3, :3], H[:3, 3]
        self.n = self.R[:, 2]
        self.c = float(self.n @ self.t)  # the plane: n . p = c

    def depth(self, x, y) -> np.ndarray:
        """Depth z_C of the hit (inf for rays parallel to the plane or meeting it behind the camera)."""
        n0, n1, n2 = self.n.tolist()
        with np.errstate(divide="ignore", invalid="ignore"):
            t = self.c / (n0 * x + n1 * y + n2)
        return np.where(t > 0, t, np.inf)

    def coords(self, x, y, t) -> tuple[np.ndarray, np.ndarray]:
        """In-plane coordinates (x_P, y_P) [mm] of the points t * (x, y, 1)."""
        r1, r2 = self.R[:, 0].tolist(), self.R[:, 1].tolist()
        xp = t * (r1[0] * x + r1[1] * y + r1[2]) - float(self.R[:, 0] @ self.t)
        yp = t * (r2[0] * x + r2[1] * y + r2[2]) - float(self.R[:, 1] @ self.t)
        return xp, yp


class _Scene:
    """The cell as the camera sees it at one instant: surfaces, their grey levels and the table texture.

    The calibration plate (a board ``PLATE_THICKNESS_MM`` thick whose z = 0 face is the printed sheet:
    paper with dark discs), the foam block under it (a larger slab whose top lies ``FOAM_GAP_MM`` behind
    the plate plane), the two fingers as boxes in G (each face lit by ``LIGHT_G`` to one of the three
    ``finger`` grey levels), and the table (the plane z = 0 of the robot base B, z up) with a seeded
    texture."""

    def __init__(self, world: SimWorld, spec: ImageSpec, backdrop: Backdrop | None = None):
        with world.lock:
            self.camera: CameraModel = world.camera
            C_H_G = world.C_H_G
            C_H_W = world.C_H_W
            C_H_B = world.C_H_B
            gap = float(world.jaw_gap_mm)
            points_G, finger_boxes = world.points_G(), world.finger_boxes_G(gap)
            imp, self.imperfect = world.imperfections, world.imperfect
            self.world_truth = world.truth()
            world_seed = world.seed
            obj = world.object
            C_H_O = world.C_H_O
        cell = world.cell
        self.C_H_G, self.C_H_W = C_H_G, C_H_W
        self.plate: PlateSpec = cell.plate
        self.imperfections = imp
        self.points_C = transform_points(C_H_G, points_G)
        self.fingers = [
            _Box(C_H_G, lo, hi, _FINGER0 + 6 * i + np.arange(6), chamfer_cuts(lo, hi, imp.finger_edge_radius_mm))
            for i, (lo, hi) in enumerate(finger_boxes)
        ]
        # the printed discs' centres on the sheet's plane (W, z = 0): a disc lifted by the bow is drawn
        # where the camera's ray through it meets the plane, so its image is where the lifted disc's is
        self.disc_centres_W = None
        if cell.plate.pattern == "discs" and (imp.plate_scale or imp.plate_dot_sd_mm or imp.plate_bow_mm):
            lifted_C = transform_points(C_H_W, self.imperfect.disc_centres_W)
            n, c0 = C_H_W[:3, 2], float(C_H_W[:3, 2] @ C_H_W[:3, 3])
            on_plane_C = lifted_C * (c0 / (lifted_C @ n))[:, None]
            self.disc_centres_W = transform_points(np.linalg.inv(C_H_W), on_plane_C)
            self.disc_centres_W[:, 2] = 0.0
        sx, sy = cell.plate.size
        board = [_BOARD_SIDE] * 6
        board[4] = _PRINT  # the z = 0 face, towards the camera side
        self.board = _Box(C_H_W, (-sx / 2, -sy / 2, 0.0), (sx / 2, sy / 2, PLATE_THICKNESS_MM), board)
        foam = [_FOAM_SIDE] * 6
        foam[4] = _FOAM_TOP
        h = FOAM_SIZE_MM / 2
        self.foam = _Box(C_H_W, (-h, -h, FOAM_GAP_MM), (h, h, FOAM_GAP_MM + FOAM_THICKNESS_MM), foam)
        self.boxes = [self.board, self.foam, *self.fingers]
        self.target = None
        if obj is not None:  # the block to grasp, its top face (z = 0 of O, towards the camera) printed
            bx, by, bh = obj.spec.block
            faces = [_BLOCK_SIDE] * 6
            faces[4] = _TARGET
            self.boxes.append(_Box(C_H_O, (-bx / 2, -by / 2, 0.0), (bx / 2, by / 2, bh), faces))
            self.target = _Plane(C_H_O)
            sigma = 0.5 * float(C_H_O[2, 3]) / float(self.camera.f) / _TARGET_RES  # a pixel's footprint
            tex, origin = _target_texture(obj.spec.target, (bx, by), spec.paper, spec.ink)
            self.target_texture = _blurred(tex, sigma)
            self.target_map = (*origin, _TARGET_RES)
        self.traced = self.boxes  # the boxes rays can meet (a backdrop takes the plate and foam away)
        self.sheet = _Plane(C_H_W)
        self.table = _Plane(C_H_B)
        # discs are printed on the side the camera looks at; from behind the sheet is plain paper
        self.print_seen = bool(self.board.o[2] < 0)
        self.texture = _table_texture(world_seed)
        self.tex_map = (_TABLE_X0, _TABLE_Y0, _TABLE_RES)  # table mm -> texel: origin x, y and mm per texel
        if backdrop is not None:
            self.traced = list(self.fingers)
            self.print_seen = False
            self.table = _Plane(backdrop.C_H_T(C_H_W))
            depth = float(self.table.depth(np.zeros(1), np.zeros(1))[0])
            depth = depth if np.isfinite(depth) else float(backdrop.C_H_T(C_H_W)[2, 3])
            self.texture = backdrop.texture(depth, float(self.camera.f))
            h, w = self.texture.shape
            r = float(backdrop.mm_per_px)
            self.tex_map = (-0.5 * w * r, -0.5 * h * r, r)
        # grey level of every label; table pixels are looked up in the texture instead
        levels = np.zeros(_N_LABELS)
        levels[[_ROOM, _FOAM_TOP, _FOAM_SIDE, _PAPER, _INK, _BOARD_SIDE]] = (
            ROOM_GRAY, spec.foam, 0.8 * spec.foam, spec.paper, spec.ink, 0.8 * spec.paper,
        )
        dark, mid, bright = sorted(spec.finger)
        lit = _FACE_NORMALS @ LIGHT_G
        face_level = np.where(lit >= 0.5, bright, np.where(lit >= 0.0, mid, dark))
        levels[_FINGER0 : _FINGER0 + 12] = np.tile(face_level, 2)
        levels[[_BLOCK_SIDE, _TARGET]] = (0.75 * spec.paper, spec.paper)
        self.levels = levels

    # -- rays --
    def trace(self, x: np.ndarray, y: np.ndarray, boxes=None) -> tuple[np.ndarray, np.ndarray]:
        """First surface along the rays (x, y, 1) of C: (depth z_C (inf: none), label).

        ``boxes`` limits the search to some of ``self.boxes`` (the table is always there)."""
        t_best = self.table.depth(x, y).astype(x.dtype)
        label = np.where(np.isfinite(t_best), _TABLE, _ROOM).astype(np.int16)
        for box in self.traced if boxes is None else [b for b in boxes if any(b is t for t in self.traced)]:
            idx = box.rays_near(x, y)
            if idx is not None and idx.size == 0:
                continue
            t, face = box.hit(x, y) if idx is None else box.hit(x[idx], y[idx])
            keep = np.flatnonzero(t < (t_best if idx is None else t_best[idx]))
            rows = keep if idx is None else idx[keep]
            t_best[rows] = t[keep]
            label[rows] = box.face_labels[face[keep]]
        printed = np.flatnonzero(label == _PRINT)
        label[printed] = _PAPER
        if self.print_seen and printed.size:
            xw, yw = self.sheet.coords(x[printed], y[printed], t_best[printed])
            label[printed[self._in_disc(xw, yw)]] = _INK
        return t_best, label

    def _in_disc(self, xw: np.ndarray, yw: np.ndarray) -> np.ndarray:
        """Whether plate points (x_W, y_W) [mm] lie on the print (a disc; a board's dark print)."""
        p = self.plate
        if p.pattern != "discs":
            return board_ink(p, xw, yw)
        c = np.clip(np.rint(xw / p.pitch + (p.cols - 1) / 2), 0, p.cols - 1)
        r = np.clip(np.rint(yw / p.pitch + (p.rows - 1) / 2), 0, p.rows - 1)
        if self.disc_centres_W is not None:  # an imperfect print (imperfections.py): each disc where it is
            k = (r * p.cols + c).astype(np.intp)
            dx, dy = xw - self.disc_centres_W[k, 0], yw - self.disc_centres_W[k, 1]
            rad = p.disc_diameter / 2 * (1.0 + self.imperfect.scale)
            return dx * dx + dy * dy <= rad**2
        dx = xw - (c - (p.cols - 1) / 2) * p.pitch
        dy = yw - (r - (p.rows - 1) / 2) * p.pitch
        return dx * dx + dy * dy <= (p.disc_diameter / 2) ** 2

    def shade(self, x: np.ndarray, y: np.ndarray, boxes=None) -> tuple[np.ndarray, np.ndarray]:
        """Grey level (float) and label of the rays (x, y, 1) of C (``boxes``: as for ``trace``)."""
        t, label = self.trace(x, y, boxes)
        value = self.levels[label]
        on_table = label == _TABLE
        if np.any(on_table):
            xb, yb = self.table.coords(x[on_table], y[on_table], t[on_table])
            value[on_table] = self.texture_at(xb, yb)
        on_target = label == _TARGET
        if self.target is not None and np.any(on_target):
            xo, yo = self.target.coords(x[on_target], y[on_target], t[on_target])
            value[on_target] = _sample_texture(self.target_texture, self.target_map, xo, yo)
        return value, label

    def shade_print(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Grey level of the rays (x, y, 1) of C (any shape) on the printed sheet's plane, nothing else."""
        t = self.sheet.depth(x, y)
        xw, yw = self.sheet.coords(x, y, t)
        ink = self._in_disc(xw, yw) & self.print_seen
        return np.where(ink, self.levels[_INK], self.levels[_PAPER])

    def texture_at(self, xb, yb) -> np.ndarray:
        """Table texture at table points (x_B, y_B) [mm] (any shape), bilinear."""
        return _sample_texture(self.texture, self.tex_map, xb, yb)


def _sample_texture(texture: np.ndarray, tex_map, xb, yb) -> np.ndarray:
    """``texture`` at plane points (x, y) [mm] (any shape), bilinear; ``tex_map`` as for ``_texel``."""
    shape = np.shape(xb)
    tx, ty = _texel(np.ravel(xb), np.ravel(yb), tex_map)
    n = tx.size
    cols = 1024
    rows = max(1, -(-n // cols))
    mx = np.zeros(rows * cols, np.float32)
    my = np.zeros(rows * cols, np.float32)
    mx[:n], my[:n] = tx, ty
    out = cv2.remap(texture, mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REFLECT_101)
    return out.ravel()[:n].astype(float).reshape(shape)


def _texel(xb, yb, tex_map=(_TABLE_X0, _TABLE_Y0, _TABLE_RES)) -> tuple[np.ndarray, np.ndarray]:
    """Table coordinates [mm] -> texel coordinates (float32), clipped far outside to keep cv2 in range;
    ``tex_map`` (x0, y0, mm per texel)."""
    x0, y0, res = tex_map
    tx = np.clip((np.asarray(xb) - x0) / res, -1e5, 1e5).astype(np.float32)
    ty = np.clip((np.asarray(yb) - y0) / res, -1e5, 1e5).astype(np.float32)
    return tx, ty


@functools.lru_cache(maxsize=4)
def _table_texture(world_seed: int) -> np.ndarray:
    """The table's seeded texture (float32 grey levels): blobs and strokes on a mid-grey top, smoothed."""
    rng = np.random.default_rng([int(world_seed), 0x7AB1E])
    n = int(_TABLE_SIZE / _TABLE_RES)
    img = np.full((n, n), 115, np.uint8)
    px = 1.0 / _TABLE_RES
    shift = 4  # cv2 drawing with 4 fractional bits
    sc = float(1 << shift)
    for _ in range(900):
        c = rng.uniform(0, n, 2)
        axes = rng.uniform(1.5, 14.0, 2) * px
        cv2.ellipse(img, (int(c[0] * sc), int(c[1] * sc)), (int(axes[0] * sc), int(axes[1] * sc)),
                    float(rng.uniform(0, 180)), 0, 360, int(rng.integers(45, 215)), -1, cv2.LINE_AA, shift)
    for _ in range(500):
        p = rng.uniform(0, n, 2) + np.cumsum(rng.normal(0, 12 * px, (int(rng.integers(2, 6)), 2)), axis=0)
        cv2.polylines(img, [(p * sc).astype(np.int32)], False, int(rng.integers(30, 230)),
                      int(rng.uniform(0.4, 2.5) * px), cv2.LINE_AA, shift)
    tex = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 1.0)
    tex.flags.writeable = False  # shared by every render of worlds with this seed
    return tex


@functools.lru_cache(maxsize=4)
def _target_texture(target, size_mm: tuple[float, float], paper: float, ink: float) -> tuple[np.ndarray, tuple]:
    """The block's top face (``size_mm`` x, y) with the ChArUco target centred on it, ``_TARGET_RES`` mm per
    texel, grey levels ``ink``..``paper`` (float32, read-only), and the O coordinates (x, y) [mm] of its
    first texel's centre."""
    w, h = (int(round(v / _TARGET_RES)) for v in size_mm)
    tw, th = (int(round(v / _TARGET_RES)) for v in target.size)
    board = target_board(target).generateImage((tw, th), marginSize=0)
    tex = np.full((h, w), 255, np.uint8)
    x0, y0 = (w - tw) // 2, (h - th) // 2
    tex[y0 : y0 + th, x0 : x0 + tw] = board
    out = (ink + (paper - ink) * (tex.astype(np.float32) / 255.0)).astype(np.float32)
    out.flags.writeable = False
    return out, ((0.5 - x0 - tw / 2) * _TARGET_RES, (0.5 - y0 - th / 2) * _TARGET_RES)


def _blurred(tex: np.ndarray, sigma: float) -> np.ndarray:
    """``tex`` smoothed by a Gaussian of ``sigma`` texels (a pixel's footprint: the texture is sampled once per ray)."""
    return cv2.GaussianBlur(tex, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE) if sigma > 0.3 else tex


# --- projection helpers ---------------------------------------------------------------------------
def _project(camera: CameraModel, p_C: np.ndarray, z_min: float = 1e-6) -> np.ndarray:
    """Camera points (N, 3) -> pixels (N, 2), NaN where a point lies behind the camera or beyond the lens's field."""
    p_C = np.asarray(p_C, float).reshape(-1, 3)
    out = np.full((len(p_C), 2), np.nan)
    ok = p_C[:, 2] > z_min
    XY = camera.f * p_C[ok, :2] / p_C[ok, 2:3]
    reach = np.hypot(XY[:, 0], XY[:, 1]) <= max_undistorted_radius(camera.kappa)
    idx = np.flatnonzero(ok)[reach]
    if idx.size:
        out[idx] = camera.distort_to_pixels(XY[reach])
    return out


def _circle_W(plate: PlateSpec, n: int, scene: "_Scene | None" = None) -> np.ndarray:
    """(rows*cols, n, 3) points on every disc's rim in W [mm] (as printed in ``scene``'s world)."""
    a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    rim = (plate.disc_diameter / 2) * np.column_stack([np.cos(a), np.sin(a), np.zeros(n)])
    if scene is not None and scene.disc_centres_W is not None:
        return scene.disc_centres_W[:, None, :] + (1.0 + scene.imperfect.scale) * rim[None, :, :]
    return plate.disc_centres_W()[:, None, :] + rim[None, :, :]


def disc_image_centroids(camera: CameraModel, C_H_W: np.ndarray, plate: PlateSpec, n: int = 4096) -> np.ndarray:
    """(rows*cols, 2) area centroid [px] of each disc's (distorted) image, NaN where a disc cannot be imaged.

    This is where the intensity-weighted centroid of a dark blob lies, which is not the image of the
    disc's centre (``RenderResult.disc_uv``): their difference is the ellipse-centre bias of a tilted
    circle under perspective and distortion. Computed exactly for the polygon of ``n`` projected rim
    points (shoelace formula), whose error falls as 1/n^2.
    """
    rim = transform_points(C_H_W, _circle_W(plate, n).reshape(-1, 3))
    uv = _project(camera, rim).reshape(-1, n, 2)
    u, v = uv[..., 0], uv[..., 1]
    un, vn = np.roll(u, -1, axis=1), np.roll(v, -1, axis=1)
    cross = u * vn - un * v
    area = cross.sum(axis=1) / 2
    cu = ((u + un) * cross).sum(axis=1) / (6 * area)
    cv = ((v + vn) * cross).sum(axis=1) / (6 * area)
    return np.column_stack([cu, cv])


# --- render ---------------------------------------------------------------------------------------
def _lattice(count: int) -> np.ndarray:
    """(N, 2) offsets in [0, 1)^2 of the Fibonacci lattice with the least Fibonacci number N >= count:
    every sample has its own row and column offset, and edges of any direction are resolved evenly."""
    a, b = 1, 2
    while b < count:
        a, b = b, a + b
    i = np.arange(b)
    return np.column_stack([(i + 0.5) / b, ((i * a) % b + 0.5) / b])


def _edge_samples(n: int) -> int:
    """Least number of rays per edge pixel for ``supersample`` n: (2 n)^2 (89 on the lattice for n = 4)."""
    return (2 * n) ** 2


def _pixel_shift(iu: np.ndarray, iv: np.ndarray) -> np.ndarray:
    """(N, 2) shifts in [0, 1)^2 per pixel, a fixed hash of its indices (Cranley-Patterson rotation of the
    lattice): each pixel's coverage estimate is unbiased, so quantisation errors do not line up along an edge."""
    mask = np.uint64(0xFFFFFFFF)
    h = (iu.astype(np.uint64) * np.uint64(0x9E3779B1) + iv.astype(np.uint64) * np.uint64(0x85EBCA77)) & mask
    h ^= h >> np.uint64(15)
    h = (h * np.uint64(0x2C1B3C6D)) & mask
    h ^= h >> np.uint64(12)
    h2 = (h * np.uint64(0x297A2D39)) & mask
    h2 ^= h2 >> np.uint64(15)
    return np.column_stack([h & np.uint64(0xFFFF), h2 & np.uint64(0xFFFF)]).astype(float) / 65536.0


def _rays(camera: CameraModel, u, v) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (u, v), any equal shapes -> rays (x, y, 1) in C through them (eq. 4 then eq. 3 inverted)."""
    XY = camera.undistort_pixels(np.column_stack([np.ravel(u), np.ravel(v)]))
    return XY[:, 0] / camera.f, XY[:, 1] / camera.f


def _edge_bits(scene: _Scene, shape: tuple[int, int], m: int) -> np.ndarray:
    """(Hm, Wm) uint8, pixel (u, v) at [v+m, u+m]: bit k set where the image of an edge of ``scene.boxes[k]``
    crosses the pixel, ``_PRINT_BIT`` where a disc rim does."""
    cam = scene.camera
    Hm, Wm = shape
    bits = np.zeros(shape, np.uint8)
    # the undistorted sensor coordinates the (margin-extended) picture spans
    s = np.linspace(0, 1, 257)
    border = np.concatenate([
        np.column_stack([-m - 0.5 + s * Wm, np.full_like(s, -m - 0.5)]),
        np.column_stack([-m - 0.5 + s * Wm, np.full_like(s, Hm - m - 0.5)]),
        np.column_stack([np.full_like(s, -m - 0.5), -m - 0.5 + s * Hm]),
        np.column_stack([np.full_like(s, Wm - m - 0.5), -m - 0.5 + s * Hm]),
    ])
    XYb = cam.undistort_pixels(border)
    lo, hi = XYb.min(axis=0) - 1.0, XYb.max(axis=0) + 1.0
    # a step along an undistorted edge grows by up to 1 / (1 + 3 kappa r^2) in the picture (kappa < 0)
    r2 = float(np.max(np.sum(cam.pixel_to_sensor(border) ** 2, axis=1)))
    step = _EDGE_STEP_PX * min(1.0, 1.0 + 3.0 * cam.kappa * r2)
    for k, box in enumerate(scene.boxes):
        if not any(box is t for t in scene.traced):
            continue
        pts = []
        for p0, p1 in box.edges_C():
            seg = _clip_segment(cam.f, p0, p1, lo, hi)
            if seg is not None:
                a, b = seg
                n = int(np.ceil(np.linalg.norm(b - a) / step)) + 1
                pts.append(a + np.linspace(0, 1, n)[:, None] * (b - a))
        if pts:
            _mark(bits, cam, np.concatenate(pts), m, np.uint8(1 << k))
    if scene.print_seen:
        rims = _rim_points(scene, lo, hi, step) if scene.plate.pattern == "discs" else _board_edge_points(scene, lo, hi, step)
        _mark(bits, cam, rims, m, np.uint8(_PRINT_BIT))
    return bits


def _rim_points(scene: _Scene, lo, hi, step: float) -> np.ndarray:
    """(N, 2) undistorted sensor coordinates along every disc rim inside lo..hi, spaced under ``step``."""
    cam, plate = scene.camera, scene.plate
    r = plate.disc_diameter / 2
    z_near = float(np.min(transform_points(scene.C_H_W, plate.disc_centres_W())[:, 2]))
    r_px = cam.f * r / max(z_near - r, 1.0)
    n = int(min(np.ceil(1.5 * 2 * np.pi * r_px / step), 20000))
    rim = transform_points(scene.C_H_W, _circle_W(plate, n, scene).reshape(-1, 3))
    rim = rim[rim[:, 2] > 1e-3]
    XY = cam.f * rim[:, :2] / rim[:, 2:3]
    return XY[np.all((XY >= lo) & (XY <= hi), axis=1)]


def _board_edge_points(scene: _Scene, lo, hi, step: float) -> np.ndarray:
    """(N, 2) undistorted sensor coordinates along the board's print edges inside lo..hi, spaced under ``step``."""
    pts = [np.zeros((0, 2))]
    for p0, p1 in board_edges_W(scene.plate):
        seg = _clip_segment(scene.camera.f, *transform_points(scene.C_H_W, np.array([p0, p1])), lo, hi)
        if seg is not None:
            a, b = seg
            n = int(np.ceil(np.linalg.norm(b - a) / step)) + 1
            pts.append(a + np.linspace(0, 1, n)[:, None] * (b - a))
    return np.concatenate(pts)


def _mark(bits: np.ndarray, cam: CameraModel, XY: np.ndarray, m: int, bit: np.uint8) -> None:
    """Set ``bit`` at the pixels within ``_EDGE_HALF_PX`` of the images of undistorted points XY (N, 2)."""
    if cam.kappa < 0:
        XY = XY[np.hypot(XY[:, 0], XY[:, 1]) < max_undistorted_radius(cam.kappa)]
    uv = cam.distort_to_pixels(XY)
    Hm, Wm = bits.shape
    for du in (-_EDGE_HALF_PX, _EDGE_HALF_PX):
        for dv in (-_EDGE_HALF_PX, _EDGE_HALF_PX):
            iu = np.floor(uv[:, 0] + 0.5 + du).astype(np.int64) + m
            iv = np.floor(uv[:, 1] + 0.5 + dv).astype(np.int64) + m
            ok = (iu >= 0) & (iu < Wm) & (iv >= 0) & (iv < Hm)
            bits[iv[ok], iu[ok]] |= bit


def _dilate_bits(bits: np.ndarray) -> np.ndarray:
    """Bitwise OR of each pixel's 3 x 3 neighbourhood (uint8 bit masks)."""
    out = np.zeros_like(bits)
    kernel = np.ones((3, 3), np.uint8)
    for k in range(8):
        plane = (bits >> k) & 1
        if plane.any():
            out |= cv2.dilate(plane, kernel) << k
    return out


def _clip_segment(f: float, p0, p1, lo, hi):
    """Clip a 3-D segment (C, mm) to z > 1e-3 mm, project it (eq. 3) and clip it to the box lo..hi of
    undistorted sensor coordinates. Returns the two end points (2,) or None."""
    z0, z1 = p0[2], p1[2]
    eps = 1e-3
    if z0 <= eps and z1 <= eps:
        return None
    if z0 <= eps or z1 <= eps:
        s = (eps - z0) / (z1 - z0)
        q = p0 + s * (p1 - p0)
        p0, p1 = (q, p1) if z0 <= eps else (p0, q)
    a = f * p0[:2] / p0[2]
    b = f * p1[:2] / p1[2]
    # Liang-Barsky in 2-D
    s0, s1 = 0.0, 1.0
    d = b - a
    for k in range(2):
        for pk, qk in ((-d[k], a[k] - lo[k]), (d[k], hi[k] - a[k])):
            if pk == 0:
                if qk < 0:
                    return None
                continue
            r = qk / pk
            if pk < 0:
                s0 = max(s0, r)
            else:
                s1 = min(s1, r)
    if s0 > s1:
        return None
    return a + s0 * d, a + s1 * d


def _shade_table(scene: _Scene, value, label, x, y, n: int) -> None:
    """Replace ``value`` (Hm, Wm) where the pixel centre sees the table by the texture's mean over an
    n x n grid in the pixel. The ray -> table map is smooth, so the grid's table coordinates are
    interpolated (bilinear) between pixel centres, exact to far below a texel; the picture is done in
    bands of rows (each with one more row on either side) to bound the memory."""
    on_table = label == _TABLE
    rows = np.flatnonzero(on_table.any(axis=1))
    if rows.size == 0:
        return
    Hm, Wm = label.shape
    t = scene.table.depth(x, y)
    tx, ty = _texel(*scene.table.coords(x, y, np.where(np.isfinite(t), t, 0.0)), scene.tex_map)
    band = max(1, _CHUNK * 8 // (n * n * Wm))
    for r0 in range(int(rows[0]), int(rows[-1]) + 1, band):
        r1 = min(r0 + band, Hm)
        a, b = max(r0 - 1, 0), min(r1 + 1, Hm)
        # cv2.resize by n puts fine row f at coarse row a + (f + 0.5) / n - 0.5: the grid of each pixel
        size = (Wm * n, (b - a) * n)
        mx = cv2.resize(tx[a:b], size, interpolation=cv2.INTER_LINEAR)[(r0 - a) * n : (r1 - a) * n]
        my = cv2.resize(ty[a:b], size, interpolation=cv2.INTER_LINEAR)[(r0 - a) * n : (r1 - a) * n]
        fine = cv2.remap(scene.texture, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
        mean = fine.reshape(r1 - r0, n, Wm, n).mean(axis=(1, 3), dtype=np.float64)
        sel = on_table[r0:r1]
        value[r0:r1][sel] = mean[sel]


def _edge_pixels(scene: _Scene, label: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pixels an edge crosses, or whose centre sees another surface than a neighbour's: (rows, columns
    of ``label`` (Hm, Wm), and for each a bit mask of the surfaces that can show up in it).

    A surface seen anywhere in a pixel either has an edge crossing the pixel's 3 x 3 neighbourhood or
    is seen at one of those nine centres; bit k stands for ``scene.boxes[k]``, ``_PRINT_BIT`` for the
    printed face; the table is always a candidate.
    """
    bits = _edge_bits(scene, label.shape, m)
    mixed = np.zeros(label.shape, bool)
    mixed[:, 1:] |= label[:, 1:] != label[:, :-1]
    mixed[:, :-1] |= label[:, 1:] != label[:, :-1]
    mixed[1:, :] |= label[1:, :] != label[:-1, :]
    mixed[:-1, :] |= label[1:, :] != label[:-1, :]
    candidates = _dilate_bits(bits | _LABEL_BITS[label])
    iv, iu = np.nonzero(mixed | (bits > 0))
    return iv, iu, candidates[iv, iu]


def _shade_edge_pixels(scene: _Scene, value, label, x, y, m: int, n: int) -> None:
    """Replace ``value`` (Hm, Wm) at the pixels an edge crosses by the mean over a lattice of rays.

    ``label``, ``x``, ``y`` (Hm, Wm): what each pixel centre sees and its ray. Each pixel's rays are
    traced only against the surfaces that can show up in it (``_edge_pixels``); where that leaves only
    the printed sheet (most disc rims) the sheet's plane alone.
    """
    cam = scene.camera
    iv, iu, groups = _edge_pixels(scene, label, m)
    # rays through the samples, linear in the offset from the pixel centre (exact to 1e-4 px at the
    # picture's corners: the second derivative of eq. 4 is 6 kappa r)
    xc, yc = x[iv, iu], y[iv, iu]
    pu, pv = (iu - m).astype(float), (iv - m).astype(float)
    xr, yr = _rays(cam, pu + 0.5, pv)
    xl, yl = _rays(cam, pu - 0.5, pv)
    xd, yd = _rays(cam, pu, pv + 0.5)
    xup, yup = _rays(cam, pu, pv - 0.5)
    jac = np.column_stack([xr - xl, xd - xup, yr - yl, yd - yup]).astype(np.float32)
    offs = _lattice(_edge_samples(n))
    per_chunk = max(1, _CHUNK // len(offs))
    for g in np.unique(groups):
        boxes = [b for k, b in enumerate(scene.boxes) if g & (1 << k) or (k == 0 and g & _PRINT_BIT)]
        (sel,) = np.nonzero(groups == g)
        for s in range(0, len(sel), per_chunk):
            j = sel[s : s + per_chunk]
            shift = _pixel_shift(iu[j], iv[j])
            du = ((offs[None, :, 0] + shift[:, 0:1]) % 1.0 - 0.5).astype(np.float32)
            dv = ((offs[None, :, 1] + shift[:, 1:2]) % 1.0 - 0.5).astype(np.float32)
            sx = xc[j, None] + jac[j, 0:1] * du + jac[j, 1:2] * dv
            sy = yc[j, None] + jac[j, 2:3] * du + jac[j, 3:4] * dv
            if g == _PRINT_BIT:
                vals = scene.shade_print(sx, sy)
            else:
                vals, _ = scene.shade(sx.ravel(), sy.ravel(), boxes)
            value[iv[j], iu[j]] = vals.reshape(du.shape).mean(axis=1)


def _lamp_light(scene: _Scene, lamp: Lamp, x: np.ndarray, y: np.ndarray, label: np.ndarray) -> np.ndarray:
    """The lamp's light factor (Hm, Wm) at the pixel centres: 1 lit, ``lamp.ambient`` in full shadow,
    between in the penumbra (the share of the lamp's sample points each surface point sees).

    Traced first at every ``_SHADOW_STEP``-th pixel, then at every pixel near a coarse one in some shadow
    (a shadow narrower than that step can be missed: the fingers' are tens of pixels wide)."""
    factor = np.ones(label.shape)
    lit = (label != _ROOM) & (label < _FINGER0)
    boxes = list(scene.fingers) + [_Box(scene.C_H_W, lo, hi, [_BOARD_SIDE] * 6) for lo, hi in lamp.occluders]
    lamp_C = transform_points(scene.C_H_W, lamp.points_W())

    def light(sel):
        xs, ys = x[sel].astype(float), y[sel].astype(float)
        t, _ = scene.trace(xs, ys)
        p = np.column_stack([xs * t, ys * t, t])
        seen = np.zeros(len(p))
        for q in lamp_C:
            blocked = np.zeros(len(p), bool)
            for box in boxes:
                blocked |= box.blocks(p, q)
            seen += ~blocked
        return lamp.ambient + (1.0 - lamp.ambient) * seen / lamp.samples

    k = _SHADOW_STEP
    coarse = np.zeros(label.shape, bool)
    coarse[::k, ::k] = True
    coarse &= lit
    factor[coarse] = light(coarse)
    shaded = (factor < 1.0).astype(np.uint8)
    near = cv2.dilate(shaded, np.ones((2 * k + 1, 2 * k + 1), np.uint8)).astype(bool) & lit & ~coarse
    if near.any():
        factor[near] = light(near)
    return factor


def _check_args(world, blur_px, gain, supersample, image_spec) -> ImageSpec:
    if not isinstance(world, SimWorld):
        raise ConfigError(f"render: expected a SimWorld, got {type(world).__name__}")
    spec = image_spec if image_spec is not None else world.cell.simulation.image
    if not isinstance(spec, ImageSpec):
        raise ConfigError(f"render image_spec: expected a selfview.files.cell.ImageSpec, got {type(spec).__name__}")
    if isinstance(supersample, bool) or not isinstance(supersample, (int, np.integer)) or not 4 <= supersample <= 16:
        raise ConfigError(
            f"render supersample: expected a whole number of samples per pixel axis, 4..16, got {supersample!r}"
        )
    if blur_px is not None and not (np.isfinite(blur_px) and 0 <= blur_px <= 10):
        raise ConfigError(f"render blur_px: expected a Gaussian sigma of 0..10 px, got {blur_px!r}")
    if not (np.isfinite(gain) and 0 < gain <= 10):
        raise ConfigError(f"render gain: expected a brightness factor in (0, 10], got {gain!r}")
    return spec


def render(world: SimWorld, *, seed: int | None = 0, noise: bool = True, blur_px: float | None = None,
           gain: float = 1.0, supersample: int = 4, image_spec: ImageSpec | None = None,
           backdrop: Backdrop | None = None, lamp: Lamp | None = None) -> RenderResult:
    """Render the wrist camera's (H, W) uint8 picture of ``world`` now, with its ground truth.

    Pixel (u, v) covers u-0.5..u+0.5, v-0.5..v+0.5. A pixel that no edge crosses sees one surface and
    takes its value exactly; one that an edge crosses (the images of all box edges and disc rims are
    marked analytically, and so is every pixel whose centre sees another surface than a neighbour's)
    averages a Fibonacci lattice of at least (2 n)^2 rays, n = ``supersample`` (89 for n = 4), shifted by
    a fixed hash of the pixel, so edges of any direction are resolved evenly and the quantisation errors
    of neighbouring pixels do not line up along an edge; a table pixel averages the texture over a
    regular n x n grid. Then optical blur, ``gain``, sensor noise, clipping and rounding to 8 bits.

    ``seed`` seeds the sensor noise (same seed, same bytes; None draws fresh noise); ``noise=False``
    gives the noise-free picture; ``blur_px`` overrides ``simulation.image.blur_px`` (Gaussian sigma,
    px); ``gain`` scales the brightness before the noise, which is
    ``numpy.random.default_rng(seed).normal(0, noise_gray, (H, W))``; ``supersample`` n, 4..16: where an
    edge crosses a pixel at least (2 n)^2 rays (89 for n = 4), on the textured table an n x n grid;
    ``image_spec`` replaces the cell's ``simulation.image``; ``backdrop`` (a ``Backdrop``) lays a picture as
    the table behind the fingertips instead of the plate, its foam and the seeded table; ``lamp`` (a
    ``Lamp``) casts the fingers' (and its occluders') shadows on the plate, its foam and the table. Raises
    ``ConfigError`` for a bad argument.
    """
    spec = _check_args(world, blur_px, gain, supersample, image_spec)
    if backdrop is not None:
        if not isinstance(backdrop, Backdrop):
            raise ConfigError(f"render backdrop: expected a selfview.mocks.render.Backdrop, got {type(backdrop).__name__}")
        backdrop.check()
    if lamp is not None:
        if not isinstance(lamp, Lamp):
            raise ConfigError(f"render lamp: expected a selfview.mocks.render.Lamp, got {type(lamp).__name__}")
        lamp.check()
    n = int(supersample)
    sigma = float(spec.blur_px if blur_px is None else blur_px)
    scene = _Scene(world, spec, backdrop)
    cam = scene.camera
    W, H = int(cam.width), int(cam.height)
    m = int(np.ceil(4 * sigma)) + 2  # render beyond the border so the blur sees the scene there
    Hm, Wm = H + 2 * m, W + 2 * m
    vv, uu = np.mgrid[-m : H + m, -m : W + m].astype(float)

    # 1. every pixel centre (single precision: 3e-8 of a ray's slope is 3e-5 px)
    x, y = (a.astype(np.float32) for a in _rays(cam, uu, vv))
    value, label = scene.shade(x, y)
    value, label = value.reshape(Hm, Wm), label.reshape(Hm, Wm)

    # 2. the table: the texture averaged over an n x n grid in each pixel
    _shade_table(scene, value, label, x.reshape(Hm, Wm), y.reshape(Hm, Wm), n)

    # 3. pixels an edge crosses, or whose centre sees another surface than a neighbour's
    _shade_edge_pixels(scene, value, label, x.reshape(Hm, Wm), y.reshape(Hm, Wm), m, n)
    if lamp is not None:
        value = value * _lamp_light(scene, lamp, x.reshape(Hm, Wm), y.reshape(Hm, Wm), label)

    # 4. optics and sensor
    if sigma > 0:
        k = cv2.getGaussianKernel(2 * int(np.ceil(4 * sigma)) + 1, sigma, cv2.CV_64F)
        value = cv2.sepFilter2D(value, cv2.CV_64F, k, k, borderType=cv2.BORDER_REFLECT)
    value, effects = picture_effects(value, scene.imperfections, scene.imperfect, seed, m, W, H, noise)  # grabber, light
    img = gain * value[m : m + H, m : m + W]
    if noise and spec.noise_gray > 0:
        img = img + np.random.default_rng(seed).normal(0.0, spec.noise_gray, img.shape)
    image = np.clip(np.rint(img), 0, 255).astype(np.uint8)

    disc_uv, disc_visible = _disc_truth(scene)
    corner_uv, corner_visible = _corner_truth(scene)
    truth = _truth_dict(scene, disc_uv, disc_visible, corner_uv, corner_visible)
    truth["render"] = {
        "noise_seed": seed, "noise": bool(noise), "noise_gray": float(spec.noise_gray), "blur_px": sigma,
        "gain": float(gain), "supersample": n, "width": W, "height": H,
    }
    if lamp is not None:
        truth["render"]["lamp"] = {"position_W": [float(v) for v in lamp.position_W], "radius_mm": float(lamp.radius_mm),
                                   "ambient": float(lamp.ambient), "samples": int(lamp.samples),
                                   "occluders": [[[float(v) for v in b] for b in box] for box in lamp.occluders]}
    if not scene.imperfections.ideal:
        truth["render"]["imperfections"] = {**scene.imperfections.as_dict(), **effects}
    return RenderResult(image, truth, disc_uv, disc_visible, corner_uv, corner_visible)


# --- ground truth ---------------------------------------------------------------------------------
def _finger_depth(scene: _Scene, x, y) -> np.ndarray:
    """Depth of the nearest finger along the rays (x, y, 1) of C (inf: none)."""
    return np.minimum(*(f.hit(x, y)[0] for f in scene.fingers))


def _disc_truth(scene: _Scene, n_rim: int = 720) -> tuple[np.ndarray, np.ndarray]:
    """Projected disc centres (N, 2) and whether each disc is whole in the picture and uncovered (N,)."""
    cam, plate = scene.camera, scene.plate
    centres_C = transform_points(scene.C_H_W, plate.disc_centres_W() if scene.disc_centres_W is None else scene.disc_centres_W)
    uv = _project(cam, centres_C)
    rim = transform_points(scene.C_H_W, _circle_W(plate, n_rim, scene).reshape(-1, 3))
    rim_uv = _project(cam, rim)
    inside = cam.in_image(np.nan_to_num(rim_uv, nan=-1e9)).reshape(-1, n_rim).all(axis=1)
    visible = inside & scene.print_seen
    if np.any(visible):
        z = np.where(rim[:, 2] > 0, rim[:, 2], np.nan)
        covered = _finger_depth(scene, rim[:, 0] / z, rim[:, 1] / z) < rim[:, 2] * (1 - 1e-9)
        visible &= ~covered.reshape(-1, n_rim).any(axis=1)
        # a finger corner poking into a disc between two rim samples
        verts = np.concatenate([f.vertices_C for f in scene.fingers])
        verts = verts[verts[:, 2] > 0]
        vx, vy = verts[:, 0] / verts[:, 2], verts[:, 1] / verts[:, 2]
        t = scene.sheet.depth(vx, vy)
        front = verts[:, 2] <= t * (1 + 1e-9)
        xw, yw = scene.sheet.coords(vx, vy, np.where(np.isfinite(t), t, 0.0))
        centres_W = plate.disc_centres_W()
        d2 = (xw[None, :] - centres_W[:, 0:1]) ** 2 + (yw[None, :] - centres_W[:, 1:2]) ** 2
        visible &= ~np.any(front[None, :] & (d2 <= (plate.disc_diameter / 2) ** 2), axis=1)
    return uv, visible


def _corner_truth(scene: _Scene) -> tuple[np.ndarray, np.ndarray]:
    """The six fingertip corners in pixels (6, 2) and whether each is in the picture and not occluded (6,)."""
    cam = scene.camera
    p = scene.points_C
    uv = _project(cam, p)
    visible = cam.in_image(np.nan_to_num(uv, nan=-1e9))
    z = np.where(p[:, 2] > 0, p[:, 2], np.nan)
    t, _ = scene.trace(p[:, 0] / z, p[:, 1] / z)
    return uv, visible & (t >= p[:, 2] * (1 - 1e-9))


def _truth_dict(scene: _Scene, disc_uv, disc_visible, corner_uv, corner_visible) -> dict:
    """The ground truth as one JSON-ready object (CONVENTIONS.md units: mm, px)."""
    plate = scene.plate

    def num(a):
        return None if not np.isfinite(a) else float(a)

    truth = dict(scene.world_truth)
    truth["C_H_G"] = scene.C_H_G.tolist()
    truth["C_H_W"] = scene.C_H_W.tolist()
    truth["discs"] = [
        [i // plate.cols, i % plate.cols, num(u), num(v), bool(vis)]
        for i, ((u, v), vis) in enumerate(zip(disc_uv, disc_visible))
    ]
    truth["corners"] = {
        name: [num(u), num(v), bool(vis)] for name, (u, v), vis in zip(POINT_NAMES, corner_uv, corner_visible)
    }
    return truth
