"""Standard ROS messages built from arrays: stamps, poses, paths, TF, point clouds and loop markers. Each builder
takes `ty`, a typestore's `types` (ROS 2's shipped definitions, slam.io.ros2.types, or a rosbags store of ROS 1
or 2), so live publishing and bag export build the same messages. Poses are `T_world_cam` 4x4 matrices, times in
seconds."""

from __future__ import annotations

import dataclasses

import numpy as np

from swarmsplat.kernels.se3 import matrix_to_quat_wxyz

LOOP_COLORS = {"intra": (0.1, 0.8, 0.2), "inter": (1.0, 0.55, 0.0)}  # green within an agent, orange between


def stamp(ty, t: float):
    sec = int(np.floor(t))
    return ty["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((t - sec) * 1e9)) % 1_000_000_000)


def header(ty, t: float, frame: str):
    return ty["std_msgs/msg/Header"](stamp=stamp(ty, t), frame_id=frame)


def quaternion(ty, R: np.ndarray):
    q = matrix_to_quat_wxyz(R)
    return ty["geometry_msgs/msg/Quaternion"](x=float(q[1]), y=float(q[2]), z=float(q[3]), w=float(q[0]))


def pose(ty, T: np.ndarray):
    return ty["geometry_msgs/msg/Pose"](
        position=ty["geometry_msgs/msg/Point"](x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
        orientation=quaternion(ty, T[:3, :3]))


def pose_stamped(ty, t: float, T: np.ndarray, frame: str = "map"):
    return ty["geometry_msgs/msg/PoseStamped"](header=header(ty, t, frame), pose=pose(ty, T))


def path(ty, stamps: np.ndarray, T: np.ndarray, frame: str = "map", t_end: float | None = None):
    """nav_msgs/Path of poses T [N, 4, 4] at `stamps` [N]; stamped at `t_end` (default: the last stamp)."""
    t_end = float(stamps[-1]) if t_end is None and len(stamps) else (t_end or 0.0)
    return ty["nav_msgs/msg/Path"](header=header(ty, t_end, frame),
                                   poses=[pose_stamped(ty, float(s), Ti, frame) for s, Ti in zip(stamps, T)])


def transform(ty, t: float, T: np.ndarray, parent: str, child: str):
    """geometry_msgs/TransformStamped `parent` -> `child` (T maps child coordinates to parent's)."""
    v = ty["geometry_msgs/msg/Vector3"](x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3]))
    return ty["geometry_msgs/msg/TransformStamped"](
        header=header(ty, t, parent), child_frame_id=child,
        transform=ty["geometry_msgs/msg/Transform"](translation=v, rotation=quaternion(ty, T[:3, :3])))


def tf(ty, t: float, transforms: list[tuple[np.ndarray, str, str]]):
    """tf2_msgs/TFMessage of (T, parent, child) transforms at time t."""
    return ty["tf2_msgs/msg/TFMessage"](transforms=[transform(ty, t, T, p, c) for T, p, c in transforms])


def point_cloud(ty, t: float, xyz: np.ndarray, rgb: np.ndarray, frame: str = "map"):
    """sensor_msgs/PointCloud2 of points xyz [N, 3] (m) with colours rgb [N, 3] (uint8): fields x, y, z (float32)
    and rgb (float32 holding 0x00RRGGBB, as PCL and rviz read it), 16 bytes a point, dense, unordered."""
    n = len(xyz)
    rec = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])
    rec["x"], rec["y"], rec["z"] = (np.asarray(xyz, np.float32)[:, k] for k in range(3))
    c = np.asarray(rgb, np.uint32).reshape(n, 3)
    rec["rgb"] = (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]
    F = ty["sensor_msgs/msg/PointField"]
    fields = [F(name=nm, offset=4 * k, datatype=7, count=1) for k, nm in enumerate(("x", "y", "z", "rgb"))]  # FLOAT32
    return ty["sensor_msgs/msg/PointCloud2"](header=header(ty, t, frame), height=1, width=n, fields=fields,
                                             is_bigendian=False, point_step=16, row_step=16 * n,
                                             data=rec.view(np.uint8).reshape(-1), is_dense=True)


def cloud_arrays(msg) -> tuple[np.ndarray, np.ndarray]:
    """(xyz [N, 3] float32, rgb [N, 3] uint8) of a PointCloud2 made by point_cloud."""
    rec = np.frombuffer(bytes(msg.data), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])
    xyz = np.stack([rec["x"], rec["y"], rec["z"]], axis=1)
    rgb = np.stack([(rec["rgb"] >> s) & 255 for s in (16, 8, 0)], axis=1).astype(np.uint8)
    return xyz, rgb


def loop_markers(ty, hdr, loops: list[tuple[np.ndarray, np.ndarray, str]]):
    """visualization_msgs/MarkerArray with one LINE_LIST per loop kind ("intra" green, "inter" orange) between the
    positions (p_i, p_j) of each loop's keyframes. Marker's fields differ between ROS 1 and ROS 2 releases, so the
    marker gets the fields its type has."""
    from swarmsplat.kernels.errors import InputError

    Point, Color = ty["geometry_msgs/msg/Point"], ty["std_msgs/msg/ColorRGBA"]
    Marker = ty["visualization_msgs/msg/Marker"]
    have = {f.name for f in dataclasses.fields(Marker)  # fields with a default are the type's constants
            if f.default is dataclasses.MISSING and f.name != "__msgtype__"}
    empty = np.zeros(0, np.uint8)
    markers = []
    for k, kind in enumerate(("intra", "inter")):
        pts = [Point(x=float(p[0]), y=float(p[1]), z=float(p[2])) for a, b, kd in loops if kd == kind for p in (a, b)]
        if not pts:
            continue
        r, g, b = LOOP_COLORS[kind]
        values = {
            "header": hdr, "ns": f"loops_{kind}", "id": k, "type": 5, "action": 0,  # LINE_LIST, ADD
            "pose": pose(ty, np.eye(4)),
            "scale": ty["geometry_msgs/msg/Vector3"](x=0.01, y=0.0, z=0.0), "color": Color(r=r, g=g, b=b, a=1.0),
            "lifetime": ty["builtin_interfaces/msg/Duration"](sec=0, nanosec=0), "frame_locked": False,
            "points": pts, "colors": [], "text": "", "mesh_resource": "", "mesh_use_embedded_materials": False,
            "texture_resource": "", "uv_coordinates": [],
        }
        if "texture" in have:
            values["texture"] = ty["sensor_msgs/msg/CompressedImage"](header=hdr, format="", data=empty)
        if "mesh_file" in have:
            values["mesh_file"] = ty["visualization_msgs/msg/MeshFile"](filename="", data=empty)
        missing = have - set(values)
        if missing:
            raise InputError(f"visualization_msgs/Marker has fields this export does not fill: {sorted(missing)}")
        markers.append(Marker(**{f: values[f] for f in have}))
    return ty["visualization_msgs/msg/MarkerArray"](markers=markers)
