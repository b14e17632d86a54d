"""A run's results as a ROS 2 bag (MCAP or SQLite) or a ROS 1 bag, in standard messages, to replay in the ROS tools
users know (rviz, Foxglove, rqt_bag, `ros2 bag play`): what `swarmsplat export RUN --to mcap|rosbag2|rosbag1`
writes.

Per agent, stamped with the frames' own stamps:
  /<agent>/pose            geometry_msgs/PoseStamped   every tracked frame, with loop closures (trajectory*.txt)
  /<agent>/pose_tracking   geometry_msgs/PoseStamped   the same frames as tracking alone placed them
  /<agent>/path            nav_msgs/Path               the whole trajectory, once, at the last frame's stamp
  /<agent>/keyframes       nav_msgs/Path               the keyframe poses, once (keyframes.txt, or the pose graph)
  /tf                      tf2_msgs/TFMessage          map -> <agent>/camera for every frame
and for the run:
  /loops                   visualization_msgs/MarkerArray   accepted loop edges as lines between keyframe
                                                            positions (green intra-agent, orange inter-agent)
A single agent's folder gives keyframes from keyframes.txt and loops from loops.csv; a team's from
pose_graph_optimized.g2o (vertices are keyframes, one symbol letter per agent in agent order; edges other than
consecutive keyframes of one agent are loops).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from swarmsplat.kernels.errors import InputError

from ..ros2 import messages as M

TARGETS = {"mcap": "mcap", "rosbag2": "db3", "rosbag1": "ros1"}


def _run_parts(run: Path) -> tuple[dict, dict, list[tuple[np.ndarray, np.ndarray, str]]]:
    """({agent: (stamps, T, T_tracking)}, {agent: (stamps, T_keyframes)}, [(p_i, p_j, kind)]) of a run folder."""
    from swarmsplat.slam.io.trajectory import read_tum

    def traj(p: Path):
        return read_tum(p) if p.is_file() else (np.zeros(0), np.zeros((0, 4, 4)))

    if (run / "trajectory.txt").is_file():  # one agent
        name = json.loads((run / "metrics.json").read_text()).get("agent", "agent") \
            if (run / "metrics.json").is_file() else "agent"
        t, T = read_tum(run / "trajectory.txt")
        _, T0 = traj(run / "trajectory_no_lc.txt")
        agents = {name: (t, T, T0 if len(T0) == len(T) else T)}
        kfs = {name: traj(run / "keyframes.txt")}
        return agents, kfs, _loops_csv(run / "loops.csv", kfs[name][1])
    if (run / "trajectories").is_dir():  # a team
        agents = {}
        for p in sorted((run / "trajectories").glob("*.txt")):
            t, T = read_tum(p)
            _, T0 = traj(run / "trajectories_no_lc" / p.name)
            agents[p.stem] = (t, T, T0 if len(T0) == len(T) else T)
        kfs, loops = _graph(run / "pose_graph_optimized.g2o", list(agents))
        return agents, kfs, loops
    raise InputError(f"{run}: not a run folder (expected trajectory.txt, or trajectories/ of a team run)")


def _loops_csv(path: Path, T_kf: np.ndarray) -> list:
    if not path.is_file() or not len(T_kf):
        return []
    out = []
    with open(path) as f:
        for row in csv.DictReader(f):
            if row.get("accepted") == "True":
                i, j = int(row["query_kf"]), int(row["match_kf"])
                if i < len(T_kf) and j < len(T_kf):
                    out.append((T_kf[i][:3, 3], T_kf[j][:3, 3], "intra"))
    return out


def _graph(path: Path, names: list[str]) -> tuple[dict, list]:
    from swarmsplat.graph.g2o import read_g2o

    if not path.is_file():
        return {}, []
    g = read_g2o(path, information="isotropic")
    chars = sorted({k >> 56 for k in g.poses})
    who = {c: names[i] if i < len(names) else chr(c) for i, c in enumerate(chars)}
    kfs = {}
    for c in chars:
        keys = sorted(k for k in g.poses if k >> 56 == c)
        kfs[who[c]] = (np.arange(len(keys), dtype=float), np.stack([g.poses[k] for k in keys]))
    loops = []
    for e in g.edges:
        same = e.key_i >> 56 == e.key_j >> 56
        if same and abs((e.key_i & (2**56 - 1)) - (e.key_j & (2**56 - 1))) == 1:
            continue  # odometry between consecutive keyframes
        loops.append((g.poses[e.key_i][:3, 3], g.poses[e.key_j][:3, 3], "intra" if same else "inter"))
    return kfs, loops


def export_run(run: str | Path, out: str | Path, to: str = "mcap", *, frame_id: str = "map") -> dict:
    """Write run folder `run` as a bag at `out` (a new path). Returns {topic: message count}."""
    from rosbags.typesys import Stores, get_typestore

    if to not in TARGETS:
        raise InputError(f"--to {to!r}: expected one of {', '.join(TARGETS)}")
    run, out = Path(run), Path(out)
    if out.exists():
        raise InputError(f"{out} exists already; a bag is written to a new path")
    agents, kfs, loops = _run_parts(run)
    ros1 = TARGETS[to] == "ros1"
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if "tf2_msgs/msg/TFMessage" not in store.types:  # ROS 1's store lacks it; its definition is one line
        from rosbags.typesys import get_types_from_msg

        store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    ty = store.types
    ser = store.serialize_ros1 if ros1 else store.serialize_cdr
    out.parent.mkdir(parents=True, exist_ok=True)
    if ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(out)
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        writer = Writer(out, version=9, storage_plugin=StoragePlugin.MCAP if to == "mcap" else StoragePlugin.SQLITE3)

    def header(t: float, frame: str = frame_id):
        H = ty["std_msgs/msg/Header"]
        return H(seq=0, stamp=M.stamp(ty, t), frame_id=frame) if ros1 else M.header(ty, t, frame)

    def stamped(t, T):
        return ty["geometry_msgs/msg/PoseStamped"](header=header(t), pose=M.pose(ty, T))

    def path_msg(t_end, stamps, Ts):
        return ty["nav_msgs/msg/Path"](header=header(t_end), poses=[stamped(float(s), T) for s, T in zip(stamps, Ts)])

    counts: dict[str, int] = {}
    with writer:
        conns = {}

        def put(topic: str, msg, t: float) -> None:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msg.__msgtype__, typestore=store)
            writer.write(conns[topic], int(round(t * 1e9)), ser(msg, msg.__msgtype__))
            counts[topic] = counts.get(topic, 0) + 1

        t_last = max((float(a[0][-1]) for a in agents.values() if len(a[0])), default=0.0)
        for name, (t, T, T0) in agents.items():
            for s, Ti, T0i in zip(t, T, T0):
                put(f"/{name}/pose", stamped(float(s), Ti), float(s))
                put(f"/{name}/pose_tracking", stamped(float(s), T0i), float(s))
                tf = ty["geometry_msgs/msg/TransformStamped"](
                    header=header(float(s)), child_frame_id=f"{name}/camera",
                    transform=ty["geometry_msgs/msg/Transform"](
                        translation=ty["geometry_msgs/msg/Vector3"](x=float(Ti[0, 3]), y=float(Ti[1, 3]),
                                                                     z=float(Ti[2, 3])),
                        rotation=M.quaternion(ty, Ti[:3, :3])))
                put("/tf", ty["tf2_msgs/msg/TFMessage"](transforms=[tf]), float(s))
            if len(t):
                put(f"/{name}/path", path_msg(float(t[-1]), t, T), float(t[-1]))
        for name, (ks, Tk) in kfs.items():
            if len(Tk):
                put(f"/{name}/keyframes", path_msg(t_last, ks, Tk), t_last)
        if loops:
            put("/loops", M.loop_markers(ty, header(t_last), loops), t_last)
    return counts

