"""ROS messages (as `rosbags` deserialises them, ROS 1 or ROS 2) into what a `Frame` holds.

Colour: RGB uint8 [H, W, 3]. Depth: float32 metres [H, W], 0 = invalid. Poses: T_world_frame 4x4 float64. Field
names differ between ROS 1 and ROS 2 only in CameraInfo (K/D against k/d); both are read.
"""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import InputError
from swarmsplat.kernels.se3 import quat_wxyz_to_matrix

IMAGE = ("sensor_msgs/msg/Image", "sensor_msgs/Image")
COMPRESSED = ("sensor_msgs/msg/CompressedImage", "sensor_msgs/CompressedImage")
CAMERA_INFO = ("sensor_msgs/msg/CameraInfo", "sensor_msgs/CameraInfo")
ODOMETRY = ("nav_msgs/msg/Odometry", "nav_msgs/Odometry")
POSE_STAMPED = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/PoseStamped")
POSE_TYPES = ODOMETRY + POSE_STAMPED
COLOR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8", "8uc1", "8uc3")
DEPTH_ENCODINGS = ("16uc1", "mono16", "32fc1")


def why(e: BaseException) -> str:
    """One line saying what a reader or a message failed on: the error's type and text, an assert's empty text
    replaced by the function whose check failed (rosbags checks a bag's records with asserts)."""
    kind = type(e).__name__
    if kind == "error":  # struct.error, cv2.error
        kind = f"{type(e).__module__}.{kind}"
    text = " ".join(str(e).split())
    if not text:
        tb = e.__traceback__
        while tb is not None and tb.tb_next is not None:
            tb = tb.tb_next
        fn = tb.tb_frame.f_code.co_name if tb is not None else "?"
        return f"a check in {fn} failed" if isinstance(e, AssertionError) else f"{kind} in {fn}"
    return f"{kind}: {text[:200]}"


@contextmanager
def _as_defined(msgtype: str, where: str | None):
    """A message read as ROS defines `msgtype`. A bag carries its own message definitions, and rosbags builds the
    message from them: a field missing or of another type is InputError naming the topic (`where`; None: the
    error as it is, for callers that name the place themselves)."""
    try:
        yield
    except InputError as e:
        if where is None or str(e).startswith(where):
            raise
        raise InputError(f"{where}: {e}") from None
    except (AttributeError, TypeError, ValueError, OverflowError, IndexError) as e:
        if where is None:
            raise
        raise InputError(f"{where}: a {msgtype} message that is not as ROS defines it ({why(e)}); expected the "
                         f"standard {msgtype}") from None


def stamp_of(msg, where: str | None = None) -> float:
    """The header stamp in seconds."""
    with _as_defined("message with a std_msgs/Header", where):
        st = msg.header.stamp
        return float(st.sec) + 1e-9 * float(st.nanosec)


def _raw(msg, where: str, bytes_per_pixel: int) -> np.ndarray:
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8)
    if h <= 0 or w <= 0 or step <= 0 or data.size < h * step:
        raise InputError(f"{where}: image message of {data.size} bytes does not hold {h} rows of {step} bytes "
                         f"({w}x{h})")
    if step < w * bytes_per_pixel:
        raise InputError(f"{where}: image rows of {step} bytes cannot hold {w} pixels of {bytes_per_pixel} bytes "
                         f"({msg.encoding}); expected a step of at least {w * bytes_per_pixel}")
    return data[: h * step].reshape(h, step)


def decode_color(msg, msgtype: str, where: str) -> np.ndarray:
    """sensor_msgs Image (rgb8, bgr8, rgba8, bgra8, mono8) or CompressedImage (jpeg, png) -> RGB uint8 [H, W, 3]."""
    with _as_defined(msgtype, where):
        return _decode_color(msg, msgtype, where)


def _decode_color(msg, msgtype: str, where: str) -> np.ndarray:
    import cv2

    if msgtype in COMPRESSED:
        img = cv2.imdecode(np.asarray(msg.data, dtype=np.uint8), cv2.IMREAD_COLOR)
        if img is None:
            raise InputError(f"{where}: compressed image (format {msg.format!r}) does not decode; expected jpeg "
                             "or png")
        return np.ascontiguousarray(img[:, :, ::-1])
    enc = str(msg.encoding).lower()
    if enc not in COLOR_ENCODINGS:
        raise InputError(f"{where}: colour encoding {msg.encoding!r} is not supported; expected one of "
                         f"{', '.join(COLOR_ENCODINGS[:5])}")
    ch = 1 if enc in ("mono8", "8uc1") else 4 if enc in ("rgba8", "bgra8") else 3
    rows = _raw(msg, where, ch)
    h, w = rows.shape[0], int(msg.width)
    img = rows[:, : w * ch].reshape(h, w, ch)
    if ch == 1:
        return np.repeat(img, 3, axis=2)
    img = img[:, :, :3]
    # a copy: the message's bytes are read-only, and the reader may reuse them
    return np.array(img[:, :, ::-1] if enc.startswith("bgr") else img, order="C")


def decode_depth(msg, msgtype: str, where: str) -> np.ndarray:
    """sensor_msgs Image (16UC1 millimetres, 32FC1 metres) or image_transport's compressedDepth PNG -> float32
    metres, 0 where invalid (0, NaN, inf)."""
    with _as_defined(msgtype, where):
        return _decode_depth(msg, msgtype, where)


def _decode_depth(msg, msgtype: str, where: str) -> np.ndarray:
    import cv2

    if msgtype in COMPRESSED:
        fmt = str(msg.format).lower()
        raw = np.asarray(msg.data, dtype=np.uint8)
        if "compresseddepth" not in fmt or "16uc1" not in fmt.replace(" ", ""):
            raise InputError(f"{where}: compressed depth format {msg.format!r} is not supported; expected "
                             "'16UC1; compressedDepth png' (image_transport)")
        img = cv2.imdecode(raw[12:], cv2.IMREAD_UNCHANGED)  # a 12-byte config header precedes the PNG
        if img is None or img.dtype != np.uint16:
            raise InputError(f"{where}: compressedDepth payload is not a 16-bit PNG")
        return img.astype(np.float32) / np.float32(1000.0)  # as the folder loaders divide
    enc = str(msg.encoding).lower()
    if enc not in DEPTH_ENCODINGS:
        raise InputError(f"{where}: depth encoding {msg.encoding!r} is not supported; expected 16UC1 "
                         "(millimetres) or 32FC1 (metres)")
    rows = _raw(msg, where, 4 if enc == "32fc1" else 2)
    h, w = rows.shape[0], int(msg.width)
    big = bool(msg.is_bigendian)
    if enc == "32fc1":
        d = rows[:, : 4 * w].copy().view(">f4" if big else "<f4").reshape(h, w).astype(np.float32)
        d[~np.isfinite(d) | (d < 0)] = 0.0
        return d
    mm = rows[:, : 2 * w].copy().view(">u2" if big else "<u2").reshape(h, w)
    return mm.astype(np.float32) / np.float32(1000.0)


def camera_from_info(msg, where: str) -> tuple[PinholeCamera, np.ndarray, str]:
    """(camera, distortion coefficients [N], distortion model) of a CameraInfo message."""
    with _as_defined("sensor_msgs/CameraInfo", where):
        K = np.asarray(getattr(msg, "k", None) if hasattr(msg, "k") else msg.K, dtype=np.float64).reshape(-1)
        D = np.asarray(getattr(msg, "d", None) if hasattr(msg, "d") else msg.D, dtype=np.float64).reshape(-1)
        if K.size != 9 or K[0] <= 0 or K[4] <= 0:
            raise InputError(f"{where}: camera_info has no valid intrinsic matrix K (got {K.tolist()[:9]})")
        cam = PinholeCamera(float(K[0]), float(K[4]), float(K[2]), float(K[5]), int(msg.width), int(msg.height))
        return cam, D, str(msg.distortion_model or "")


def pose_of(msg, msgtype: str, where: str | None = None) -> np.ndarray:
    """T_world_frame [4, 4] of a nav_msgs/Odometry or geometry_msgs/PoseStamped message."""
    with _as_defined(msgtype, where):
        pose = msg.pose.pose if msgtype in ODOMETRY else msg.pose
        p, q = pose.position, pose.orientation
        T = np.eye(4)
        T[:3, :3] = quat_wxyz_to_matrix(np.array([q.w, q.x, q.y, q.z], dtype=np.float64))
        T[:3, 3] = [p.x, p.y, p.z]
        return T
