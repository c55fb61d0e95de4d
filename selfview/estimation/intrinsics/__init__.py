"""Multi-view calibration of the interior orientation: f, kappa, principal point, aspect and skew.

Pictures of the plate from several poses separate the principal point and the aspect from f and the plate's tilt,
which one picture (Tsai's method, as the paper uses it) cannot.
"""

from selfview.estimation.intrinsics.advice import (MAX_MORE_VIEWS, STOP_ASPECT_REL, STOP_CENTRE_PX, VIEW_KINDS,
                                                   more_views_advice)
from selfview.estimation.intrinsics.calibrate import IntrinsicsResult, calibrate_intrinsics
from selfview.estimation.intrinsics.checks import (AGREE_SIGMAS, CAMERA_CHI2_LIMIT, CAMERA_FILE_MAX_EXCESS_PX,
                                                   TARGET_ACROSS_MM, TARGET_ALONG_MM, camera_check, camera_file_fit,
                                                   tcp_sigma)
from selfview.estimation.intrinsics.fit import (INTRINSIC_NAMES, MIN_VIEWS, ViewFit, detect_views, fit_views,
                                                guess_camera, initial_pose, projection_sigma_px, view_tilt_distance)
from selfview.estimation.intrinsics.plate import PLATE_MODELS

__all__ = [
    "AGREE_SIGMAS", "CAMERA_CHI2_LIMIT", "CAMERA_FILE_MAX_EXCESS_PX", "INTRINSIC_NAMES", "IntrinsicsResult",
    "MAX_MORE_VIEWS", "MIN_VIEWS", "PLATE_MODELS", "STOP_ASPECT_REL", "STOP_CENTRE_PX", "TARGET_ACROSS_MM",
    "TARGET_ALONG_MM", "VIEW_KINDS", "ViewFit", "calibrate_intrinsics", "camera_check", "camera_file_fit",
    "detect_views", "fit_views", "guess_camera", "initial_pose", "more_views_advice", "projection_sigma_px",
    "tcp_sigma", "view_tilt_distance",
]
