"""``selfview export``: a calibration file in the formats the rest of a lab reads (OpenCV, ROS, JSON).

The camera goes out as OpenCV's camera matrix and distortion, fitted to the paper's one-coefficient
kappa model over the whole picture (the fit's residual stated in the file), and ``C_H_G`` as a
transform with both frames named and its direction written out.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from selfview.procedures.commands._common import output_file, print_json

#: The wrist camera's optical frame: x along the picture's rows, y down its columns, z along the optical axis,
#: which ROS names ``*_optical_frame`` (REP 103: "suffix frames with _optical"; REP 105).
CAMERA_FRAME = "camera_optical_frame"
CAMERA_NAME = "camera"  # camera_info's camera_name: the device, not a frame
GRIPPER_FRAME = "gripper_tcp"  # G: the gripper's TCP between the fingertips
DIRECTION = (f"C_H_G maps {GRIPPER_FRAME} coordinates to {CAMERA_FRAME} coordinates: p_camera = C_H_G p_gripper_tcp; "
             f"it is the pose of {GRIPPER_FRAME} in the camera's optical frame (parent {CAMERA_FRAME}, child "
             f"{GRIPPER_FRAME}; x right, y down, z along the optical axis); lengths in mm, in metres in the ROS file")


def register(sub):
    p = sub.add_parser(
        "export",
        help="write a calibration as OpenCV FileStorage YAML, ROS camera_info + transform YAML, or JSON",
        description=(
            "Writes the camera (OpenCV's camera matrix K and plumb_bob distortion k1 k2 p1 p2 k3, or the rational model's 8 "
            "coefficients where plumb_bob misses by over 0.05 px; fitted to the "
            "calibration's kappa model over a grid of the whole picture; the fit's RMS and maximum in pixels are "
            "written beside them) and C_H_G as a transform from frame gripper_tcp to frame camera_optical_frame (REP 103). opencv: one "
            "FileStorage YAML (cv2.FileStorage reads it); ros: OUT is sensor_msgs/CameraInfo YAML and "
            "NAME.transform.yaml beside it (NAME: OUT up to its first dot) a geometry_msgs/TransformStamped (metres, quaternion x y z w); json: one file."
        ),
    )
    p.add_argument("calibration", metavar="CAL.yaml", help="calibration file (from selfview calibrate)")
    p.add_argument("--format", required=True, choices=("opencv", "ros", "json"))
    p.add_argument("--out", metavar="FILE", help="file to write (default: CAL with .opencv.yml, .camera_info.yaml "
                                                  "or .export.json)")
    p.add_argument("--json", action="store_true", help="print what was written as one JSON object on stdout")
    p.set_defaults(func=run)
    return p


def opencv_camera(camera, grid: int = 40, plumb_bob_max_px: float = 0.05) -> dict:
    """OpenCV's K and distortion for ``camera`` (``selfview.maths.camera.CameraModel``): K from f, the aspect, the
    skew and the centre; the radial coefficients by linear least squares so that OpenCV's forward model maps
    each undistorted ray to the pixel the kappa model gives, over a ``grid`` x ``grid`` lattice of the whole
    picture. plumb_bob (k1 k2 p1 p2 k3) when it holds to ``plumb_bob_max_px``, else OpenCV's rational model
    (k1 k2 p1 p2 k3 k4 k5 k6, ROS's rational_polynomial). Returns {K, dist, model, rms_px, max_px} (the
    residual against the kappa model, with K's skew term applied; ``skew_dropped_max_px``: how far
    cv2.projectPoints, which drops that term, moves a pixel)."""
    import cv2

    f, a = camera.f, camera.aspect
    K = np.array([[f / a, camera.skew * f, camera.cx], [0.0, f, camera.cy], [0.0, 0.0, 1.0]])
    u, v = np.meshgrid(np.linspace(0, camera.width - 1, grid), np.linspace(0, camera.height - 1, grid))
    uv = np.column_stack([u.ravel(), v.ravel()])
    xd = camera.pixel_to_sensor(uv) / f  # distorted, normalised
    xu = camera.undistort_pixels(uv) / f  # undistorted, normalised: the ray (x, y, 1)
    r2 = np.sum(xu**2, axis=1)
    powers = np.column_stack([r2, r2**2, r2**3])
    b = np.concatenate([xd[:, 0] - xu[:, 0], xd[:, 1] - xu[:, 1]])
    rays = np.column_stack([xu, np.ones(len(xu))])
    for model in ("plumb_bob", "rational_polynomial"):
        # x_d (1 + k4 r^2 + k5 r^4 + k6 r^6) = x_u (1 + k1 r^2 + k2 r^4 + k3 r^6): linear in the k
        A = np.vstack([xu[:, 0:1] * powers, xu[:, 1:2] * powers])
        if model == "rational_polynomial":
            A = np.column_stack([A, -np.vstack([xd[:, 0:1] * powers, xd[:, 1:2] * powers])])
        k = np.linalg.lstsq(A, b, rcond=None)[0]
        dist = np.array([k[0], k[1], 0.0, 0.0, *k[2:]])
        # OpenCV's distortion, then the whole K (cv2.projectPoints itself drops K's skew term)
        xd_cv, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), np.eye(3), dist)
        back = np.column_stack([xd_cv.reshape(-1, 2), np.ones(len(uv))]) @ K.T
        err = np.linalg.norm(back[:, :2] - uv, axis=1)
        if err.max() <= plumb_bob_max_px:
            break
    dropped, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, dist)
    return {"K": K, "dist": dist, "model": model, "rms_px": float(np.sqrt(np.mean(err**2))), "max_px": float(err.max()),
            "skew_dropped_max_px": float(np.linalg.norm(dropped.reshape(-1, 2) - back[:, :2], axis=1).max())}


def _quaternion(R) -> list[float]:
    """x y z w of a rotation matrix."""
    from selfview.maths.geometry import rotvec_from_R

    rv = rotvec_from_R(R)
    th = float(np.linalg.norm(rv))
    axis = rv / th if th > 1e-12 else np.zeros(3)
    return [*(axis * np.sin(th / 2)).tolist(), float(np.cos(th / 2))]


def _atomic_write_text(path: Path, text: str) -> None:
    """The export's file, by the atomic writer (no temporary file left, the old file kept on failure)."""
    from selfview.errors import ConfigError
    from selfview.files.io_safe import atomic_write

    atomic_write(path, text.encode("utf-8"), error=ConfigError, what="export")


def run(args) -> int:
    import cv2
    import yaml

    from selfview.files.calfile import load_calibration
    from selfview.errors import ConfigError

    cal = load_calibration(args.calibration)
    cam = cal.camera
    fit = opencv_camera(cam)
    src = Path(args.calibration)
    default = {"opencv": ".opencv.yml", "ros": ".camera_info.yaml", "json": ".export.json"}[args.format]
    out = Path(args.out) if args.out else src.with_name(src.stem + default)
    output_file(str(out), "--out")
    H = np.asarray(cal.C_H_G, float)
    fit_note = (f"OpenCV {fit['model']} fitted to the kappa model (kappa {cam.kappa:.6e} px^-2) over the whole picture: "
                f"rms {fit['rms_px']:.4f} px, max {fit['max_px']:.4f} px"
                + (f"; K[0][1] holds the grabber's shear (skew {cam.skew:.6f}), which cv2.projectPoints and "
                   f"cv2.undistortPoints drop: {fit['skew_dropped_max_px']:.3f} px at most" if cam.skew else ""))
    written = [str(out)]
    if args.format == "opencv":
        ext = out.suffix.lower()
        if ext not in (".yml", ".yaml", ".xml"):
            raise ConfigError(f"--out {out}: OpenCV cannot write this file (its extension must be .yml, .yaml or .xml)")
        # written in memory (OpenCV never sees the path), then by the atomic writer
        fs = cv2.FileStorage("export" + ext, cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
        fs.write("image_width", int(cam.width))
        fs.write("image_height", int(cam.height))
        fs.write("camera_matrix", fit["K"])
        fs.write("distortion_coefficients", fit["dist"].reshape(1, -1))
        fs.write("distortion_model", fit["model"])
        fs.write("distortion_fit_rms_px", fit["rms_px"])
        fs.write("distortion_fit_max_px", fit["max_px"])
        fs.write("skew_dropped_by_opencv_max_px", fit["skew_dropped_max_px"])
        fs.write("distortion_fit", fit_note)
        fs.write("C_H_G", H)
        fs.write("C_H_G_from_frame", GRIPPER_FRAME)
        fs.write("C_H_G_to_frame", CAMERA_FRAME)
        fs.write("C_H_G_direction", DIRECTION)
        fs.write("source", src.name)
        _atomic_write_text(out, fs.releaseAndGetString())
    elif args.format == "ros":
        K = fit["K"]
        P = np.column_stack([K, np.zeros(3)])
        info = {
            "image_width": int(cam.width), "image_height": int(cam.height), "camera_name": CAMERA_NAME,
            "camera_matrix": {"rows": 3, "cols": 3, "data": K.ravel().tolist()},
            "distortion_model": fit["model"],
            "distortion_coefficients": {"rows": 1, "cols": len(fit["dist"]), "data": fit["dist"].tolist()},
            "rectification_matrix": {"rows": 3, "cols": 3, "data": np.eye(3).ravel().tolist()},
            "projection_matrix": {"rows": 3, "cols": 4, "data": P.ravel().tolist()},
        }
        _atomic_write_text(out, f"# {fit_note}\n# from {src.name}\n" + yaml.safe_dump(info, sort_keys=False))
        tf = {"header": {"frame_id": CAMERA_FRAME}, "child_frame_id": GRIPPER_FRAME,
              "transform": {"translation": dict(zip("xyz", (H[:3, 3] / 1000.0).tolist())),
                            "rotation": dict(zip("xyzw", _quaternion(H[:3, :3])))}}
        tf_path = out.with_name(out.name.split(".")[0] + ".transform.yaml")
        _atomic_write_text(tf_path, f"# {DIRECTION}\n# from {src.name}\n" + yaml.safe_dump(tf, sort_keys=False))
        written.append(str(tf_path))
    else:
        doc = {"source": src.name,
               "camera": {"width": cam.width, "height": cam.height, "f_px": cam.f, "kappa_per_px2": cam.kappa,
                          "principal_point_px": [cam.cx, cam.cy], "aspect": cam.aspect, "skew": cam.skew,
                          "opencv": {"camera_matrix": fit["K"].tolist(), "distortion_model": fit["model"],
                                     "distortion_coefficients": fit["dist"].tolist(),
                                     "fit_rms_px": fit["rms_px"], "fit_max_px": fit["max_px"]}},
               "C_H_G": {"matrix": H.tolist(), "from_frame": GRIPPER_FRAME, "to_frame": CAMERA_FRAME,
                         "direction": DIRECTION, "units": "mm"}}
        _atomic_write_text(out, json.dumps(doc, indent=1) + "\n")
    if args.json:
        print_json({"format": args.format, "written": written, "distortion_model": fit["model"], "fit_rms_px": fit["rms_px"],
                    "fit_max_px": fit["max_px"], "skew_dropped_max_px": fit["skew_dropped_max_px"]})
    else:
        print(f"written {', '.join(written)}; {fit_note}")
    return 0
