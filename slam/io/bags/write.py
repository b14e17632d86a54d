"""A sequence written as a bag, as an RGB-D camera driver records it: `<ns>/color/image_raw` (sensor_msgs/Image
rgb8, or CompressedImage jpeg/png), `<ns>/depth/image_raw` (16UC1 millimetres, or 32FC1 metres when the
sequence's depth is not whole millimetres), `<ns>/color/camera_info`, and the ground truth (`/ground_truth/pose`)
and odometry (`/odom`, nav_msgs/Odometry) as the sequence has them. For users who want a bag from a folder, and for
the tests, which check that a bag and its folder give the same run."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from swarmsplat.kernels.errors import InputError

from ..ros2 import messages as M

FORMATS = ("mcap", "db3", "ros1")


def _header(types, ros1: bool, t: float, frame: str, seq: int):
    H = types["std_msgs/msg/Header"]
    return H(seq=seq, stamp=M.stamp(types, t), frame_id=frame) if ros1 else M.header(types, t, frame)


def write_bag(sequence, path: str | Path, fmt: str = "mcap", *, namespace: str = "/camera",
              color: str = "rgb8", depth: str = "auto", frames: int | None = None) -> Path:
    """Write the first `frames` (all) frames of `sequence` to `path` (a new file for ros1, a new folder for
    mcap / db3). color: "rgb8" (raw) | "jpeg" | "png" (CompressedImage); depth: "16UC1" | "32FC1" | "auto".
    `sequence` may also be a dict {namespace: sequence} (a team in one bag: `/robot1/camera/...`; the poses go to
    `/robot1/ground_truth/pose` and `/robot1/odom`, under the namespace's first part)."""
    from rosbags.typesys import Stores, get_typestore

    if fmt not in FORMATS:
        raise InputError(f"bag format {fmt!r} is not one of {', '.join(FORMATS)}")
    path = Path(path)
    if path.exists():
        raise InputError(f"{path} exists already; a bag is written to a new path")
    path.parent.mkdir(parents=True, exist_ok=True)
    ros1 = fmt == "ros1"
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    team = isinstance(sequence, dict)
    parts = sequence if team else {namespace: sequence}
    if ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3)
    ser = store.serialize_ros1 if ros1 else store.serialize_cdr
    with writer:
        for ns, seq in parts.items():
            pose_ns = "/" + ns.strip("/").split("/")[0] if team else ""  # the agent's namespace
            _write_one(writer, store, ser, ros1, seq, ns, pose_ns, color, depth, frames)
    return path


def _write_one(writer, store, ser, ros1: bool, sequence, namespace: str, pose_ns: str, color: str, depth: str,
               frames: int | None) -> None:
    import cv2

    types = store.types
    n = len(sequence) if frames is None else min(frames, len(sequence))
    cam = sequence.camera
    if depth == "auto":
        scale = getattr(sequence, "depth_scale", None)
        depth = "16UC1" if scale in (1000, 1000.0) else "32FC1"
    Image, Compressed = types["sensor_msgs/msg/Image"], types["sensor_msgs/msg/CompressedImage"]
    Info = types["sensor_msgs/msg/CameraInfo"]
    compressed = color in ("jpeg", "png")

    def conn(topic, msgtype):
        return writer.add_connection(topic, msgtype, typestore=store)

    c_color = conn(f"{namespace}/color/image_raw" + ("/compressed" if compressed else ""),
                   (Compressed if compressed else Image).__msgtype__)
    c_depth = conn(f"{namespace}/depth/image_raw", Image.__msgtype__) if getattr(sequence, "is_rgbd", True) \
        else None
    c_info = conn(f"{namespace}/color/camera_info", Info.__msgtype__)
    c_gt = conn(f"{pose_ns}/ground_truth/pose", types["geometry_msgs/msg/PoseStamped"].__msgtype__) \
        if sequence.gt_poses is not None else None
    c_odom = conn(f"{pose_ns}/odom", types["nav_msgs/msg/Odometry"].__msgtype__) \
        if sequence.odometry is not None else None
    K = [cam.fx, 0.0, cam.cx, 0.0, cam.fy, cam.cy, 0.0, 0.0, 1.0]
    P = [cam.fx, 0.0, cam.cx, 0.0, 0.0, cam.fy, cam.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    roi = types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    for i in range(n):
        f = sequence[i]
        rec = int(round(f.timestamp * 1e9))
        hdr = _header(types, ros1, f.timestamp, "camera_color_optical_frame", i)
        if compressed:
            ok, buf = cv2.imencode("." + color, np.ascontiguousarray(f.color[:, :, ::-1]))
            msg = Compressed(header=hdr, format=color, data=np.asarray(buf, dtype=np.uint8).reshape(-1))
        else:
            msg = Image(header=hdr, height=cam.height, width=cam.width, encoding="rgb8", is_bigendian=0,
                        step=3 * cam.width, data=np.ascontiguousarray(f.color).reshape(-1))
        writer.write(c_color, rec, ser(msg, msg.__msgtype__))
        if c_depth is not None and f.depth is not None:
            if depth == "16UC1":
                raw, step = np.rint(f.depth * np.float32(1000.0)).astype("<u2"), 2 * cam.width
            else:
                raw, step = f.depth.astype("<f4"), 4 * cam.width
            msg = Image(header=hdr, height=cam.height, width=cam.width, encoding=depth, is_bigendian=0, step=step,
                        data=raw.view(np.uint8).reshape(-1))
            writer.write(c_depth, rec + 1000, ser(msg, msg.__msgtype__))  # 1 us after: recorded after colour
        if i == 0 or i == n - 1:
            d = np.zeros(5)
            fields = dict(D=d, K=np.array(K), R=np.eye(3).reshape(-1), P=np.array(P)) if ros1 else \
                dict(d=d, k=np.array(K), r=np.eye(3).reshape(-1), p=np.array(P))
            msg = Info(header=hdr, height=cam.height, width=cam.width, distortion_model="plumb_bob",
                       binning_x=0, binning_y=0, roi=roi, **fields)
            writer.write(c_info, rec + 2000, ser(msg, msg.__msgtype__))
        if c_gt is not None and f.T_world_cam_gt is not None:
            msg = types["geometry_msgs/msg/PoseStamped"](header=hdr, pose=M.pose(types, f.T_world_cam_gt))
            writer.write(c_gt, rec + 3000, ser(msg, msg.__msgtype__))
        if c_odom is not None and f.T_world_cam_odom is not None:
            PwC = types["geometry_msgs/msg/PoseWithCovariance"](pose=M.pose(types, f.T_world_cam_odom),
                                                                 covariance=np.zeros(36))
            TwC = types["geometry_msgs/msg/TwistWithCovariance"](
                twist=types["geometry_msgs/msg/Twist"](linear=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                                                       angular=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
                covariance=np.zeros(36))
            msg = types["nav_msgs/msg/Odometry"](header=hdr, child_frame_id="camera", pose=PwC, twist=TwC)
            writer.write(c_odom, rec + 4000, ser(msg, msg.__msgtype__))
