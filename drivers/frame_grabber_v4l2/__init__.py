"""The CCIR frame grabber over V4L2, and the same interface on recordings and registered sources.

Only ``selfview.drivers.frame_grabber_v4l2.capture`` uses OpenCV's capture API (``cv2.VideoCapture``).
"""

from selfview.drivers.frame_grabber_v4l2.capture import (
    EndOfStream,
    FrameSource,
    RecordedSource,
    SourceFactory,
    V4L2Source,
    register_source,
    source_for,
    to_grey,
    unregister_source,
)
from selfview.drivers.frame_grabber_v4l2.grabber import Frame, FrameGrabber, field_image
from selfview.drivers.frame_grabber_v4l2.url import STANDARDS, GrabberUrl, parse_grabber_url
from selfview.drivers.frame_grabber_v4l2.v4l2 import V4L2Device

__all__ = [
    "Frame",
    "FrameGrabber",
    "field_image",
    "FrameSource",
    "SourceFactory",
    "EndOfStream",
    "RecordedSource",
    "V4L2Source",
    "V4L2Device",
    "register_source",
    "unregister_source",
    "source_for",
    "to_grey",
    "GrabberUrl",
    "parse_grabber_url",
    "STANDARDS",
]
