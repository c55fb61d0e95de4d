"""An independent renderer of the self-viewing cell, used only by the image-pipeline tests.

The image pipeline must also be judged on pictures the project's renderer (``mocks/render.py``) did not
make, so this one follows the conventions (``tests/data/spec/CONVENTIONS.md``) with a deliberately
different technique and look, and nothing from the project's camera model or geometry: a slip in the
project's convention (say, half a pixel in the principal point) then shows as a disagreement with this
renderer's own ground truth. Lengths in mm, pixels with integer values at pixel centres.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import cv2
import numpy as np



__all__ = ["AltOptions", "AltPicture", "Case", "case", "disc_centroids", "grid_symmetry", "render", "render_world"]

# Surface labels: discs are DISC0 + index, finger faces FINGER0 + 6 * finger + face, occluders OCC0 + i.
NOTHING, TABLE, FOAM, PAPER = 0, 1, 2, 3
FINGER0, OCC0, DISC0 = 10, 30, 100
FOAM_HALF_MM = 100.0  # the foam block under the plate: 200 mm square, its top in the plate's plane


@dataclass
class AltOptions:
    """How a picture looks. Grey levels 0..255 before illumination, gain and noise."""

    paper: float = 212.0
    ink: float = 28.0
    foam: float = 128.0
    table: float = 172.0  # a light, mottled table with darker stains
    table_contrast: float = 35.0
    finger_albedo: tuple[float, float] = (0.52, 0.47)  # fingers A, B
    ambient: float = 0.22
    light_C: tuple[float, float, float] = (15.0, 70.0, 10.0)  # point light, camera frame [mm]
    specular: float = 40.0  # grey added at the centre of the strip on finger A's front face; 0: none
    blur_sigma: float = 0.6  # px, Gaussian
    gain: float = 1.0
    noise: float = 2.0  # std in grey levels at grey 128; grows with sqrt(level)
    gradient: tuple[float, float] = (0.06, -0.04)  # relative illumination change across the width, height
    vignetting: float = 0.08  # relative loss at the picture's corners
    occluders: tuple = ()  # ((min_C (3,), max_C (3,), grey), ...): boxes aligned with C [mm]
    jpeg_quality: int | None = None
    supersample: int = 4
    fingers: bool = True
    C_H_T: np.ndarray | None = None  # table plane z = 0; default 40 mm beyond the plate or 120 mm beyond the TCP
    # a picture (h, w) grey 0..255 laid on the table instead of its mottled texture, centred on the table's
    # origin at table_mm_per_px, mirrored beyond its border; table_defocus_mm: its blur (Gaussian sigma) on the table
    table_image: np.ndarray | None = None
    table_mm_per_px: float = 0.2
    table_defocus_mm: float = 0.0
    seed: int = 0
    # a real CCIR grabber (magnitudes and sources in selfview.mocks.imperfections), see _grabber
    field_shift_px: tuple[float, float] = (0.0, 0.0)  # motion of the picture between the even and odd field
    line_jitter_px: float = 0.0  # sd of each line's horizontal shift
    pll_shear_px: float = 0.0  # horizontal shift from the first line to the last
    analog_noise: float = 0.0  # sd of noise smeared along the line (grey levels)
    flicker_gain: float = 1.0  # this frame's brightness against the mean


@dataclass
class AltPicture:
    """A rendered picture and its ground truth (all pixel coordinates distorted, as in the picture)."""

    image: np.ndarray  # (H, W) uint8
    disc_uv: np.ndarray  # (rows*cols, 2) projections of the disc centres, NaN without a plate
    disc_centroid_uv: np.ndarray  # (rows*cols, 2) centroids of the discs' image regions
    disc_visible: np.ndarray  # (rows*cols,) whole disc inside the picture and unoccluded
    disc_seen: np.ndarray  # (rows*cols,) some of the disc visible
    corner_uv: np.ndarray  # (6, 2) fingertip points, POINT_NAMES order
    corner_visible: np.ndarray  # (6,) inside the picture and not hidden
    camera: object  # the camera rendered, as given (its f, kappa, cx, cy, aspect, width, height were used)
    C_H_G: np.ndarray
    C_H_W: np.ndarray | None
    gap_mm: float
    labels: np.ndarray = field(repr=False, default=None)  # (H, W) surface label at pixel centres


# --- the camera and the geometry, from the conventions and the cell's numbers --------------------------
class _Camera:
    """The camera of CONVENTIONS.md from plain numbers: eq. 1-4, both ways; with a grabber's ``skew`` (the
    line v sampled skew (v - cy) px to the right: u = X^ / aspect + skew Y^ + cx), 0 unless the camera has one.

    Projected with this module's own code from the conventions (``X^ = aspect (u - cx)``, ``Y^ = v - cy``,
    ``X = X^ (1 + kappa r^2)``, ``X = f x / z``; the inverse of the radial correction by Newton's method on
    the radius), never through ``selfview.maths.camera``."""

    NEWTON_STEPS = 40  # the radius's Newton iteration: quadratic, converged in a handful; bounded

    def __init__(self, camera):
        self.f = float(camera.f)
        self.kappa = float(camera.kappa)
        self.cx, self.cy = float(camera.cx), float(camera.cy)
        self.aspect = float(camera.aspect)
        self.skew = float(getattr(camera, "skew", 0.0))
        self.width, self.height = int(camera.width), int(camera.height)

    def undistort_pixels(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels (M, 2) -> undistorted sensor coordinates (X, Y) (M, 2), explicit (eq. 4)."""
        uv = np.asarray(uv, float)
        Yh = uv[:, 1] - self.cy
        Xh = self.aspect * (uv[:, 0] - self.cx - self.skew * Yh)
        k = 1.0 + self.kappa * (Xh * Xh + Yh * Yh)
        return np.column_stack([Xh * k, Yh * k])

    def project(self, p_C: np.ndarray) -> np.ndarray:
        """Camera points (M, 3) [mm] -> distorted pixels (M, 2): perspective, then the radius r^ of the
        distorted sensor point solved from r^ (1 + kappa r^^2) = r by Newton's method (NaN where the
        correction cannot be inverted)."""
        p = np.asarray(p_C, float).reshape(-1, 3)
        with np.errstate(divide="ignore", invalid="ignore"):
            X = self.f * p[:, 0] / p[:, 2]
            Y = self.f * p[:, 1] / p[:, 2]
        r = np.hypot(X, Y)
        rh = r.copy()
        for _ in range(self.NEWTON_STEPS):
            g = rh + self.kappa * rh**3 - r
            dg = 1.0 + 3.0 * self.kappa * rh * rh
            with np.errstate(divide="ignore", invalid="ignore"):
                step = g / dg
            rh = rh - step
            if not np.any(np.abs(step) > 1e-13 * (1.0 + r)):
                break
        bad = ~(1.0 + 3.0 * self.kappa * rh * rh > 0) | ~(p[:, 2] > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(r > 0, rh / np.where(r > 0, r, 1.0), 1.0)
        uv = np.column_stack([X * s / self.aspect + self.skew * (Y * s) + self.cx, Y * s + self.cy])
        uv[bad] = np.nan
        return uv

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(M,) pixel positions inside the picture (pixel centres at integers), ``margin`` px from its border."""
        uv = np.asarray(uv, float)
        with np.errstate(invalid="ignore"):
            return (
                (uv[:, 0] >= -0.5 + margin) & (uv[:, 0] <= self.width - 0.5 - margin)
                & (uv[:, 1] >= -0.5 + margin) & (uv[:, 1] <= self.height - 0.5 - margin)
            )  # fmt: skip


def _hom(R: np.ndarray, t) -> np.ndarray:
    H = np.eye(4)
    H[:3, :3] = R
    H[:3, 3] = t
    return H


def _inv(H: np.ndarray) -> np.ndarray:
    R = H[:3, :3]
    return _hom(R.T, -R.T @ H[:3, 3])


def _apply(H: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Points p (M, 3) mapped by the 4x4 H."""
    p = np.asarray(p, float).reshape(-1, 3)
    return p @ H[:3, :3].T + H[:3, 3]


def _disc_centres(plate) -> np.ndarray:
    """(rows*cols, 3) disc centres in W: index row * cols + col, x along a row (growing column), y along a
    column (growing row), the grid centred on W's origin, z = 0."""
    rows, cols, pitch = int(plate.rows), int(plate.cols), float(plate.pitch)
    k = np.arange(rows * cols)
    x = (k % cols - (cols - 1) / 2) * pitch
    y = (k // cols - (rows - 1) / 2) * pitch
    return np.column_stack([x, y, np.zeros(len(k))])


def _finger_boxes(gripper, gap: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """[(min, max)] of fingers A (+x) and B (-x) in G: A in x [g/2, g/2 + t], y [-w/2, w/2], z [-L, 0]."""
    g, w = float(gap), float(gripper.finger_width)
    t, L = float(gripper.finger_thickness), float(gripper.finger_length)
    return [
        (np.array([g / 2, -w / 2, -L]), np.array([g / 2 + t, w / 2, 0.0])),
        (np.array([-g / 2 - t, -w / 2, -L]), np.array([-g / 2, w / 2, 0.0])),
    ]


def _fingertips(gripper, gap: float) -> np.ndarray:
    """(6, 3) the fingertip points of the spec's table, in its order (A/B inner front/back, outer fronts)."""
    g, w, t = float(gap), float(gripper.finger_width), float(gripper.finger_thickness)
    return np.array([[g / 2, -w / 2, 0], [g / 2, w / 2, 0], [-g / 2, -w / 2, 0], [-g / 2, w / 2, 0],
                     [g / 2 + t, -w / 2, 0], [-g / 2 - t, -w / 2, 0]], float)  # fmt: skip


# --- procedural textures --------------------------------------------------------------------------
class _ValueNoise:
    """Smooth random texture: bilinear interpolation of a seeded random lattice, several octaves."""

    def __init__(self, rng: np.random.Generator, octaves=((12.0, 1.0), (3.0, 0.5), (0.8, 0.25))):
        self.octaves = [(scale, amp, rng.uniform(-1, 1, size=(97, 97))) for scale, amp in octaves]
        self.norm = sum(a for _, a, _ in self.octaves)

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        out = np.zeros_like(x)
        for scale, amp, lat in self.octaves:
            gx, gy = x / scale, y / scale
            ix, iy = np.floor(gx), np.floor(gy)
            fx, fy = gx - ix, gy - iy
            i0 = np.mod(ix, 97).astype(np.intp)
            j0 = np.mod(iy, 97).astype(np.intp)
            i1, j1 = (i0 + 1) % 97, (j0 + 1) % 97
            v = (
                lat[j0, i0] * (1 - fx) * (1 - fy)
                + lat[j0, i1] * fx * (1 - fy)
                + lat[j1, i0] * (1 - fx) * fy
                + lat[j1, i1] * fx * fy
            )
            out += amp * v
        return out / self.norm


# --- ray casting -----------------------------------------------------------------------------------
def _affine(H: np.ndarray, p: np.ndarray) -> np.ndarray:
    """H (4, 4) or (3, 3) applied to points p (M, 3), column by column (numpy's matmul is slow for
    a tall (M, 3) by (3, 3) product)."""
    R = H[:3, :3]
    out = p[:, 0:1] * R[:, 0] + p[:, 1:2] * R[:, 1] + p[:, 2:3] * R[:, 2]
    return out + H[:3, 3] if H.shape == (4, 4) else out


def _slab(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """Ray/box intersection in the box's frame. o (3,), d (M, 3). Returns (t_near, t_far, entry axis,
    entry side -1/+1); t_near = inf where the ray misses or the box lies behind."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (lo - o) * inv
        t2 = (hi - o) * inv
    tmin = np.where(np.isnan(t1), -np.inf, np.minimum(t1, t2))
    tmax = np.where(np.isnan(t1), np.inf, np.maximum(t1, t2))
    axis = np.argmax(tmin, axis=1)
    t_near = tmin[np.arange(len(d)), axis]
    t_far = np.min(tmax, axis=1)
    hit = (t_near <= t_far) & (t_near > 1e-9)
    side = np.where(d[np.arange(len(d)), axis] > 0, -1, 1)
    return np.where(hit, t_near, np.inf), t_far, axis, side


class _Scene:
    def __init__(self, camera, C_H_G, C_H_W, gap_mm: float, cell, opt: AltOptions):
        self.cam = _Camera(camera)
        self.opt = opt
        self.C_H_G = np.asarray(C_H_G, float)
        self.C_H_W = None if C_H_W is None else np.asarray(C_H_W, float)
        self.plate = cell.plate
        self.gripper = cell.gripper
        self.gap = float(gap_mm)
        rng = np.random.default_rng(opt.seed + 7919)
        self.table_tex = _ValueNoise(rng)
        self.foam_tex = _ValueNoise(rng, octaves=((1.5, 1.0), (0.5, 0.6)))
        if opt.C_H_T is not None:
            self.C_H_T = np.asarray(opt.C_H_T, float)
        elif self.C_H_W is not None:
            self.C_H_T = self.C_H_W @ _hom(np.eye(3), (0, 0, 40.0))
        else:
            self.C_H_T = self.C_H_G @ _hom(np.eye(3), (0, 0, 120.0))
        self.boxes = _finger_boxes(self.gripper, self.gap) if opt.fingers else []
        self.G_H_C = _inv(self.C_H_G)
        self.table_img = None
        if opt.table_image is not None:
            tex = np.asarray(opt.table_image, np.float32)
            if tex.ndim != 2:
                raise ValueError(f"table_image: expected a grey (h, w) picture, got shape {tex.shape}")
            s = opt.table_defocus_mm / opt.table_mm_per_px
            self.table_img = cv2.GaussianBlur(tex, (0, 0), s, borderType=cv2.BORDER_REFLECT_101) if s > 0.05 else tex

    def _table_picture(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The table picture's grey level at table points (x, y) [mm], bilinear."""
        h, w = self.table_img.shape
        n, cols = len(x), 4096  # cv2.remap takes maps under 32767 wide: rows of 4096
        rows = max(1, -(-n // cols))
        mx = np.zeros(rows * cols, np.float32)
        my = np.zeros(rows * cols, np.float32)
        mx[:n] = x / self.opt.table_mm_per_px + 0.5 * w - 0.5
        my[:n] = y / self.opt.table_mm_per_px + 0.5 * h - 0.5
        out = cv2.remap(self.table_img, mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REFLECT_101)
        return out.ravel()[:n].astype(float)

    def rays(self, uv: np.ndarray) -> np.ndarray:
        XY = self.cam.undistort_pixels(uv)
        return np.column_stack([XY / self.cam.f, np.ones(len(XY))])

    def cast(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Label (M,) and grey level (M,) seen through pixel positions uv (M, 2)."""
        d = self.rays(uv)
        m = len(d)
        opt = self.opt
        # nearest hit first, shading only for the surface that wins
        t_tab, p_tab = self._plane(self.C_H_T, d)
        t_best = t_tab.copy()
        label = np.where(np.isfinite(t_tab), TABLE, NOTHING).astype(np.int32)
        if self.C_H_W is not None:
            t_pl, p_W = self._plane(self.C_H_W, d)
            x, y = p_W[:, 0], p_W[:, 1]
            on_foam = (np.abs(x) <= FOAM_HALF_MM) & (np.abs(y) <= FOAM_HALF_MM) & (t_pl < t_best)
            t_best[on_foam] = t_pl[on_foam]
            label[on_foam] = FOAM
            sx, sy = self.plate.size
            on_paper = on_foam & (np.abs(x) <= sx / 2) & (np.abs(y) <= sy / 2)
            label[on_paper] = PAPER
            pl = self.plate
            c = np.rint(x / pl.pitch + (pl.cols - 1) / 2)
            r = np.rint(y / pl.pitch + (pl.rows - 1) / 2)
            dx = x - (c - (pl.cols - 1) / 2) * pl.pitch
            dy = y - (r - (pl.rows - 1) / 2) * pl.pitch
            ink = (
                on_paper
                & (c >= 0) & (c < pl.cols) & (r >= 0) & (r < pl.rows)
                & (dx * dx + dy * dy <= (pl.disc_diameter / 2) ** 2)
            )
            label[ink] = DISC0 + (r[ink] * pl.cols + c[ink]).astype(np.int32)
        o_G = self.G_H_C[:3, 3]
        d_G = _affine(self.G_H_C[:3, :3], d)
        finger_hits = []
        for k, (lo, hi) in enumerate(self.boxes):
            t, _, axis, side = _slab(o_G, d_G, lo, hi)
            sel = t < t_best
            t_best[sel] = t[sel]
            label[sel] = FINGER0 + 6 * k + axis[sel] * 2 + (side[sel] > 0)
            finger_hits.append((t, axis, side))
        for i, (lo, hi, _) in enumerate(opt.occluders):
            t, _, _, _ = _slab(np.zeros(3), d, np.asarray(lo, float), np.asarray(hi, float))
            sel = t < t_best
            t_best[sel], label[sel] = t[sel], OCC0 + i
        # shading
        grey = np.full(m, 60.0)
        sel = label == TABLE
        if np.any(sel):
            x, y = p_tab[sel, 0], p_tab[sel, 1]
            stain = self.table_tex(x * 0.37 + 211.0, y * 0.37 - 57.0) > 0.45  # a few sharp stains
            grey[sel] = opt.table + opt.table_contrast * self.table_tex(x, y) - 40.0 * stain
            if self.table_img is not None:
                grey[sel] = self._table_picture(x, y)
        if self.C_H_W is not None:
            sel = label == FOAM
            grey[sel] = opt.foam + 18.0 * self.foam_tex(p_W[sel, 0], p_W[sel, 1])
            grey[label == PAPER] = opt.paper
            grey[label >= DISC0] = opt.ink
        R_CG = self.C_H_G[:3, :3]
        L = np.asarray(opt.light_C, float)
        for k, ((lo, hi), (t, axis, side)) in enumerate(zip(self.boxes, finger_hits)):
            sel = (label >= FINGER0 + 6 * k) & (label < FINGER0 + 6 * k + 6)
            if not np.any(sel):
                continue
            n_G = np.zeros((int(sel.sum()), 3))
            n_G[np.arange(len(n_G)), axis[sel]] = side[sel]
            n_C = n_G @ R_CG.T
            p_C = d[sel] * t[sel, None]
            to_l = L - p_C
            dist = np.linalg.norm(to_l, axis=1)
            lam = np.clip(np.sum(n_C * to_l, axis=1) / dist, 0, None)
            g = 255.0 * opt.finger_albedo[k] * (opt.ambient + (1 - opt.ambient) * lam * (120.0 / dist) ** 2)
            if k == 0 and opt.specular > 0:
                # smooth highlight along finger A's front face (normal -y), 40 % across its thickness
                p_G = o_G + d_G[sel] * t[sel, None]
                front = (axis[sel] == 1) & (side[sel] < 0)
                xc = lo[0] + 0.4 * (hi[0] - lo[0])
                g = g + front * opt.specular * np.exp(-(((p_G[:, 0] - xc) / 0.9) ** 2))
            grey[sel] = g
        for i, (_, _, level) in enumerate(opt.occluders):
            grey[label == OCC0 + i] = float(level)
        return label, grey

    @staticmethod
    def _plane(C_H_P, d):
        """Hit distance (M,) along rays d and the hit points in frame P (M, 3) for the plane z_P = 0."""
        n = C_H_P[:3, 2]
        p0 = C_H_P[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (n @ p0) / (d @ n)
        t = np.where(np.isfinite(t) & (t > 0), t, np.inf)
        tt = np.where(np.isfinite(t), t, 0.0)
        p_P = _affine(_inv(C_H_P), d * tt[:, None])
        return t, p_P

    def blocked(self, p_C: np.ndarray) -> np.ndarray:
        """(M,) whether the straight line from the camera to points p_C (M, 3) passes through a finger
        or an occluder before reaching them (grazing a box along an edge does not count)."""
        d = p_C
        out = np.zeros(len(d), bool)
        o_G = self.G_H_C[:3, 3]
        d_G = _affine(self.G_H_C[:3, :3], d)
        tests = [(o_G, d_G, lo, hi) for lo, hi in self.boxes]
        tests += [(np.zeros(3), d, np.asarray(lo, float), np.asarray(hi, float)) for lo, hi, _ in self.opt.occluders]
        for o, dd, lo, hi in tests:
            t_near, t_far, _, _ = _slab(o, dd, lo, hi)
            # the point sits at t = 1; blocked if the ray runs inside the box for a while before it
            inside = np.minimum(t_far, 1.0) - t_near
            out |= (t_near < 1.0 - 1e-7) & (inside > 1e-6)
        return out


def _illumination(cam: _Camera, opt: AltOptions) -> np.ndarray:
    v, u = np.mgrid[0 : cam.height, 0 : cam.width].astype(float)
    xu = (u - (cam.width - 1) / 2) / cam.width
    yv = (v - (cam.height - 1) / 2) / cam.height
    r2 = (xu**2 + yv**2) / 0.5  # 1 at the corners
    return (1 + opt.gradient[0] * xu + opt.gradient[1] * yv) * (1 - opt.vignetting * r2)


def _grabber(img: np.ndarray, opt: AltOptions) -> np.ndarray:
    """A CCIR camera and grabber's imperfections on the optical picture (H, W) float, by linear
    interpolation along each line and between lines (a different technique from the project renderer's
    resampling): the odd lines sample the picture moved by ``field_shift_px`` (the second field, 20 ms
    later); each line is moved along u by a seeded N(0, line_jitter_px) plus the PLL shear (linear from 0
    on the first line to ``pll_shear_px`` on the last); then noise of sd ``analog_noise`` averaged over 3
    neighbours along the line, and the flicker gain."""
    du_f, dv_f = opt.field_shift_px
    if not (du_f or dv_f or opt.line_jitter_px or opt.pll_shear_px or opt.analog_noise or opt.flicker_gain != 1.0):
        return img
    rng = np.random.default_rng(opt.seed + 15485863)
    H, W = img.shape
    out = img.copy()
    if dv_f:
        rows = np.arange(1, H, 2)
        src = np.clip(rows - dv_f, 0, H - 1)
        r0 = np.floor(src).astype(int)
        r1 = np.minimum(r0 + 1, H - 1)
        a = (src - r0)[:, None]
        out[1::2] = (1 - a) * img[r0] + a * img[r1]
    shift = rng.normal(0.0, opt.line_jitter_px, H) + opt.pll_shear_px * np.arange(H) / max(H - 1, 1)
    shift[1::2] += du_f
    u = np.arange(W, dtype=float)
    for v in np.flatnonzero(shift):
        out[v] = np.interp(u - shift[v], u, out[v])
    if opt.analog_noise:
        n = rng.normal(0.0, opt.analog_noise * np.sqrt(3.0), (H, W + 2))
        out = out + (n[:, :-2] + n[:, 1:-1] + n[:, 2:]) / 3.0
    return out * opt.flicker_gain


def _disc_truth(scene: _Scene) -> tuple[np.ndarray, ...]:
    """Projected centres, area centroids of the distorted disc images, whole-and-visible, partly seen."""
    pl, cam = scene.plate, scene.cam
    n = pl.rows * pl.cols
    nan = np.full((n, 2), np.nan)
    if scene.C_H_W is None:
        return nan, nan.copy(), np.zeros(n, bool), np.zeros(n, bool)
    centres = _disc_centres(pl)
    uv = cam.project(_apply(scene.C_H_W, centres))
    centroid = _centroids(cam, scene.C_H_W, centres, pl.disc_diameter / 2)
    R = pl.disc_diameter / 2
    # visibility from the boundary (and two inner rings and the centre)
    t = np.arange(72) * 2 * np.pi / 72
    ring = np.column_stack([R * np.cos(t), R * np.sin(t), np.zeros_like(t)])
    probe = np.vstack([ring, 0.5 * ring, [[0.0, 0.0, 0.0]]])
    pts_C = _apply(scene.C_H_W, (centres[:, None, :] + probe[None]).reshape(-1, 3))
    ok = (cam.in_image(cam.project(pts_C), margin=0.5) & ~scene.blocked(pts_C)).reshape(n, -1)
    visible = np.all(ok[:, : len(ring)], axis=1)
    seen = np.any(ok, axis=1)
    return uv, centroid, visible, seen


def disc_centroids(camera, C_H_W, plate) -> np.ndarray:
    """(rows*cols, 2) the centroid [px] of each disc's distorted image (where a dark blob's centroid lies),
    by this module's own projection and an area integral (not the project's boundary polygon): the
    camera as plain numbers (f, kappa, cx, cy, aspect), ``plate`` its rows, cols, pitch, disc_diameter."""
    return _centroids(_Camera(camera), np.asarray(C_H_W, float), _disc_centres(plate), float(plate.disc_diameter) / 2)


def _centroids(cam: _Camera, C_H_W: np.ndarray, centres: np.ndarray, R: float) -> np.ndarray:
    n = len(centres)
    # centroid of the image region: integrate u |J| and |J| over the disc in W (Gauss-Legendre in the
    # radius, uniform in the angle; J the Jacobian of W (x, y) -> distorted pixels by central differences)
    xg, wg = np.polynomial.legendre.leggauss(12)
    rho = (xg + 1) / 2 * R
    w_rho = wg / 2 * R * rho
    phi = np.arange(96) * 2 * np.pi / 96
    dxy = np.stack(np.meshgrid(rho, phi, indexing="ij"), -1).reshape(-1, 2)
    off = np.column_stack([dxy[:, 0] * np.cos(dxy[:, 1]), dxy[:, 0] * np.sin(dxy[:, 1])])
    wq = np.repeat(w_rho, len(phi)) * (2 * np.pi / len(phi))
    h = 1e-4

    def proj(xy):
        p = np.column_stack([xy, np.zeros(len(xy))])
        return cam.project(_apply(C_H_W, p))

    q = (centres[:, None, :2] + off[None]).reshape(-1, 2)
    ju = (proj(q + [h, 0]) - proj(q - [h, 0])) / (2 * h)
    jv = (proj(q + [0, h]) - proj(q - [0, h])) / (2 * h)
    det = (np.abs(ju[:, 0] * jv[:, 1] - ju[:, 1] * jv[:, 0]) * np.tile(wq, n)).reshape(n, -1)
    return np.einsum("kq,kqi->ki", det, proj(q).reshape(n, -1, 2)) / det.sum(1)[:, None]


def render(camera, C_H_G, C_H_W, gap_mm: float, cell, options: AltOptions | None = None, **kw) -> AltPicture:
    """Render one picture of the cell: the plate at ``C_H_W`` (or none), the fingers at ``C_H_G`` with jaw
    gap ``gap_mm``. ``camera``: anything with the numbers f, kappa, cx, cy, aspect, width, height; ``cell``:
    anything with ``plate`` (rows, cols, pitch, disc_diameter, size) and ``gripper`` (finger_width,
    finger_thickness, finger_length). Options as an ``AltOptions`` or keyword arguments overriding its
    defaults.

    Per-pixel ray casting (the viewing ray of a (sub-)pixel position is exact, because eq. 4 maps
    distorted pixels to undistorted sensor coordinates explicitly); adaptive supersampling (one ray at
    each pixel centre, then ``supersample``^2 stratified, randomly jittered rays in every pixel whose 3x3
    neighbourhood sees more than one surface); fingers shaded by a point light (Lambert with fall-off and
    ambient), an optional specular strip on finger A's front face; a textured foam block under the plate
    and a textured table; image-space illumination gradient and vignetting, Gaussian blur, gain,
    Poisson-like noise, optional JPEG compression. The disc grid, finger blocks and fingertip points are
    built here from the spec's formulas and the cell's plain numbers. The returned truth: projected disc
    centres, which discs are whole and unoccluded, the centroid of each disc's (distorted) image by area
    integration, and the six fingertip corner pixels with their visibility."""
    opt = options or AltOptions()
    if kw:
        opt = AltOptions(**{**opt.__dict__, **kw})
    scene = _Scene(camera, C_H_G, C_H_W, gap_mm, cell, opt)
    H, W = scene.cam.height, scene.cam.width
    v, u = np.mgrid[0:H, 0:W]
    label, grey = scene.cast(np.column_stack([u.ravel(), v.ravel()]).astype(float))
    label = label.reshape(H, W)
    grey = grey.reshape(H, W)
    # pixels whose 3x3 neighbourhood sees more than one surface get supersampled
    pad = np.pad(label, 1, mode="edge")
    mixed = np.zeros((H, W), bool)
    for dv in (-1, 0, 1):
        for du in (-1, 0, 1):
            mixed |= pad[1 + dv : 1 + dv + H, 1 + du : 1 + du + W] != label
    mixed = cv2.dilate(mixed.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    S = max(1, int(opt.supersample))
    if S > 1 and np.any(mixed):
        rng = np.random.default_rng(opt.seed + 104729)
        mv, mu = np.nonzero(mixed)
        si, sj = np.meshgrid(np.arange(S), np.arange(S), indexing="ij")
        si, sj = si.ravel(), sj.ravel()
        acc = np.zeros(len(mu))
        chunk = max(1, 400_000 // (S * S))
        for a in range(0, len(mu), chunk):
            pu, pv = mu[a : a + chunk], mv[a : a + chunk]
            jit = rng.uniform(0, 1, size=(len(pu), S * S, 2))
            su = pu[:, None] - 0.5 + (si[None, :] + jit[..., 0]) / S
            sv = pv[:, None] - 0.5 + (sj[None, :] + jit[..., 1]) / S
            _, g = scene.cast(np.column_stack([su.ravel(), sv.ravel()]))
            acc[a : a + chunk] = g.reshape(len(pu), S * S).mean(1)
        grey[mv, mu] = acc
    img = grey * _illumination(scene.cam, opt)
    if opt.blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), opt.blur_sigma, borderType=cv2.BORDER_REFLECT)
    img = _grabber(img, opt)
    img = img * opt.gain
    if opt.noise > 0:
        nrng = np.random.default_rng(opt.seed)
        sd = opt.noise * np.sqrt(np.clip(img, 1.0, None) / 128.0)
        img = img + nrng.normal(size=img.shape) * sd
    img8 = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    if opt.jpeg_quality is not None:
        ok, buf = cv2.imencode(".jpg", img8, [cv2.IMWRITE_JPEG_QUALITY, int(opt.jpeg_quality)])
        assert ok
        img8 = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    disc_uv, disc_centroid, disc_visible, disc_seen = _disc_truth(scene)
    pts_G = _fingertips(cell.gripper, gap_mm)
    pts_C = _apply(scene.C_H_G, pts_G)
    corner_uv = scene.cam.project(pts_C)
    corner_visible = scene.cam.in_image(corner_uv, margin=0.5) & (~scene.blocked(pts_C) if opt.fingers else False)
    return AltPicture(
        image=img8,
        disc_uv=disc_uv,
        disc_centroid_uv=disc_centroid,
        disc_visible=disc_visible,
        disc_seen=disc_seen,
        corner_uv=corner_uv,
        corner_visible=np.asarray(corner_visible, bool),
        camera=camera,
        C_H_G=scene.C_H_G,
        C_H_W=scene.C_H_W,
        gap_mm=float(gap_mm),
        labels=label,
    )


def render_world(world, *, plate: bool | None = None, options: AltOptions | None = None, **kw) -> AltPicture:
    """Render the true state of a ``selfview.mocks.world.SimWorld``; the plate is shown while parked (or as told)."""
    with world.lock:
        show = world.parked if plate is None else plate
        return render(
            world.camera,
            world.C_H_G,
            world.C_H_W if show else None,
            world.jaw_gap_mm,
            world.cell,
            options,
            **kw,
        )


@dataclass
class Case:
    """A simulated situation and its picture: ``world`` the true state after it; ``C_H_G_pred`` where
    the fingertips are predicted from (the cell's mount guess while parked, the mount before the
    disturbance on-line); ``pic`` the picture and its truth."""

    cell: object
    world: object
    C_H_G_pred: np.ndarray
    pic: AltPicture


@functools.lru_cache(maxsize=48)
def case(cell_path: str, seed: int, *, turn_deg: float | None = None, online: str | None = None,
         options: tuple = ()) -> Case:
    """Memoised picture of a seeded ``SimWorld``: parked on the plate at a random offset and turn
    (``turn_deg`` fixes the turn), or with ``online`` ('cable' or 'tilt') lifted off the plate over the
    table and its camera disturbed by that series. ``options`` (name, value) pairs of ``AltOptions``;
    the noise seed is the world's."""
    from selfview.mocks.world import SimWorld  # tests only: the renderer itself does not need the world
    from selfview.files.cell import load_cell

    cell = load_cell(cell_path)
    world = SimWorld(cell, seed)
    world.park(turn_deg=turn_deg)
    pred = cell.mount_guess_C_H_G
    if online:
        pred = world.C_H_G
        world.unpark()
        world.disturb(online)
    opts = dict(options)
    opts.setdefault("seed", seed)
    return Case(cell, world, pred, render_world(world, **opts))


def grid_symmetry(det, plate, truth_uv):
    """Match detections to the truth's discs (nearest projected centre) and find the grid symmetry that
    maps the detector's W onto the true W: (index into the truth per detection, W_true_H_W_det (4, 4))."""
    d = np.linalg.norm(det.uv[:, None, :] - truth_uv[None, :, :], axis=2)
    k = np.argmin(d, axis=1)
    assert np.all(d[np.arange(len(k)), k] < 1.0), "a detection lies off every disc"
    assert len(set(k.tolist())) == len(k), "two detections on one disc"
    a, b = det.p_W[:, :2], _disc_centres(plate)[k, :2]
    U, _, Vt = np.linalg.svd((a - a.mean(0)).T @ (b - b.mean(0)))
    R = (U @ Vt).T
    R3 = np.eye(3)
    R3[:2, :2] = R
    H = _hom(R3, np.r_[b.mean(0) - R @ a.mean(0), 0.0])
    return k, H
