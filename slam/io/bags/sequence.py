"""`BagSequence`: one agent's frames read lazily from a ROS 1 bag, a ROS 2 bag (.db3 / .mcap + metadata.yaml) or
a bare .mcap file, through `rosbags` (no ROS install).

Opening a bag indexes it once: every colour and depth message's record time and header stamp (deserialised one
at a time and dropped), the first camera info, and the odometry / ground-truth poses. Colour and depth pair by
header stamp, one to one, closest first (as TUM's associate tool); poses attach to a frame from the nearest stamp
within `pose_max_diff`. Frames are then read on demand: in order, from one stream that keeps at most a few
messages ahead; out of order, from the frame's record time. Memory holds the index (a few numbers per frame),
not the images, whatever the bag's length.

A bag cut short (a recording killed mid-write) is read up to its last complete message, with a warning.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import InputError

from ..datasets._sequence import FramesBase, _row, poses_at
from ..datasets.associate import associate_unique
from ..datasets.base import Frame
from .decode import camera_from_info, decode_color, decode_depth, pose_of, stamp_of, why
from .topics import TopicChoice

_AHEAD = 32  # messages kept from the stream for later frames before it is restarted instead
_EXPECTED = {".bag": "a ROS 1 bag (#ROSBAG V2.0)", ".mcap": "an MCAP file", ".db3": "a ROS 2 bag's SQLite file"}
_FOLDER = "a ROS 2 bag folder (metadata.yaml and its .db3 or .mcap files)"


def open_reader(path: Path, *, warn: bool = True):
    """An opened rosbags AnyReader on `path` (ROS 1 .bag, ROS 2 folder, bare .mcap / .db3). A ROS 1 bag or a bare
    .mcap cut short is read up to its last complete record, with a warning (warn=False: silently)."""
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.typesys import Stores, get_typestore

    from .truncated import tolerant_reader, truncation_of

    ros1 = path.suffix == ".bag"
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    try:
        if path.suffix in (".mcap", ".bag"):
            reader = tolerant_reader(path, store)
        else:
            reader = AnyReader([path], default_typestore=store)
        reader.open()
    except InputError:  # what slam.io.bags.truncated says of a damaged bag: already one line naming it
        raise
    except AnyReaderError as e:
        raise InputError(f"{path}: cannot open as a bag: {' '.join(str(e).split())}") from None
    except SyntaxError as e:  # rosbags execs the Python it generates from the bag's message definitions
        raise InputError(f"{path}: cannot open as a bag: its message definitions do not make Python types "
                         f"({why(e)}); expected ROS message definitions") from None
    except Exception as e:  # noqa: BLE001 - rosbags lets asserts, struct, zstd, lz4 and codegen errors through
        raise InputError(f"{path}: cannot open as a bag: {why(e)}; expected {_EXPECTED.get(path.suffix, _FOLDER)}"
                         ) from None
    odd = next((c for c in reader.connections if not (isinstance(c.topic, str) and isinstance(c.msgtype, str)
                                                        and c.topic and c.msgtype)), None)
    if odd is not None:  # an SQLite bag's columns hold any type; an MCAP channel's topic may be empty
        reader.close()
        raise InputError(f"{path}: a topic named {odd.topic!r} of type {odd.msgtype!r}; expected a name and a type "
                         "(text) for every topic")
    at = truncation_of(reader)
    if at is not None and warn:
        warnings.warn(f"{path}: the file ends mid-record (a recording cut short); read its {reader.message_count} "
                      f"complete messages, up to byte {at} of {path.stat().st_size}", stacklevel=3)
    return reader


class BagSequence(FramesBase):
    """A `Sequence` (slam.io.datasets.base) over one agent's topics of a bag."""

    def __init__(self, path: str | Path, topics: TopicChoice, *, name: str | None = None,
                 camera: PinholeCamera | None = None, max_diff: float = 0.02, pose_max_diff: float = 0.05,
                 undistort: bool = True):
        self.root = Path(path)
        self.topics = topics
        self.name = name or self.root.stem
        self._reader = open_reader(self.root)
        try:
            conns = {c.topic: c for c in self._reader.connections}
            self._color_conn = conns[topics.color]
            self._depth_conn = conns.get(topics.depth) if topics.depth else None
            self._maps = None
            self._index(conns, camera, max_diff, pose_max_diff, undistort)
        except BaseException:  # a bag refused: its file closed now, not whenever the reader is collected
            self.close()
            raise
        self._stream = None  # (generator, index of the next frame it serves)
        self._stash: dict[tuple[str, int], tuple[object, bytes]] = {}

    # ---- index --------------------------------------------------------------------------------------------

    def _where(self, topic: str) -> str:
        return f"{self.root}: topic {topic}"

    def _index(self, conns, camera, max_diff, pose_max_diff, undistort) -> None:
        t = self.topics
        wanted = [conns[x] for x in (t.color, t.depth, t.info, t.odometry, t.gt) if x]
        rows: dict[str, list] = {x: [] for x in (t.color, t.depth, t.odometry, t.gt) if x}
        info = None
        sizes: dict[str, tuple[int, int]] = {}
        try:
            for conn, rec_ns, raw in self._reader.messages(connections=wanted):
                if not isinstance(rec_ns, int):  # an SQLite bag's columns hold any type
                    raise InputError(f"{self._where(conn.topic)}: a message recorded at {rec_ns!r}; expected a "
                                     "time in integer nanoseconds")
                msg = self._reader.deserialize(raw, conn.msgtype)
                if conn.topic == t.info:
                    info = info or msg
                    continue
                if conn.topic in (t.color, t.depth):
                    if conn.topic not in sizes:  # the first of each: its encoding and size (decoded once)
                        sizes[conn.topic] = self._size_of_first(conn, msg)
                    rows[conn.topic].append((rec_ns, stamp_of(msg, self._where(conn.topic))))
                else:
                    where = self._where(conn.topic)
                    rows[conn.topic].append((stamp_of(msg, where), pose_of(msg, conn.msgtype, where)))
        except InputError:
            raise
        except Exception as e:  # noqa: BLE001 - rosbags raises assorted errors on a bag cut mid-message
            warnings.warn(f"{self.root}: the bag ends early ({type(e).__name__}: {e}); read up to its last complete "
                          "message", stacklevel=2)
        color = np.array(rows[t.color], dtype=np.float64).reshape(-1, 2)
        if len(color) == 0:
            raise InputError(f"{self._where(t.color)}: no message")
        if t.depth:
            depth = np.array(rows[t.depth], dtype=np.float64).reshape(-1, 2)
            if len(depth) == 0:
                raise InputError(f"{self._where(t.depth)}: no message")
            if t.depth in sizes and sizes[t.depth] != sizes[t.color]:
                raise InputError(f"{self.root}: colour {t.color} is {sizes[t.color][0]}x{sizes[t.color][1]} but depth "
                                 f"{t.depth} is {sizes[t.depth][0]}x{sizes[t.depth][1]}; expected depth registered "
                                 "to the colour camera (e.g. aligned_depth_to_color)")
            i, j = associate_unique(color[:, 1], depth[:, 1], max_diff)
            if len(i) == 0:
                raise InputError(f"{self.root}: no colour and depth stamps within {max_diff} s of each other")
            color, depth = color[i], depth[j]
            self._depth_rec = depth[:, 0].astype(np.int64)
        self._color_rec = color[:, 0].astype(np.int64)
        self._t = color[:, 1].copy()
        self.camera = self._camera(info, camera, sizes[t.color], undistort)
        self._gt = self._poses(rows.get(t.gt), pose_max_diff) if t.gt else None
        self._odom = self._poses(rows.get(t.odometry), pose_max_diff) if t.odometry else None

    def _size_of_first(self, conn, msg) -> tuple[int, int]:
        decode = decode_depth if conn.topic == self.topics.depth else decode_color
        img = decode(msg, conn.msgtype, self._where(conn.topic))
        return int(img.shape[1]), int(img.shape[0])

    def _camera(self, info, camera, size, undistort) -> PinholeCamera:
        if camera is not None:
            return camera
        if info is None:
            raise InputError(f"{self.root}: no camera_info topic for {self.topics.color}; give one with --topics "
                             "info=TOPIC (or pass camera= from Python)")
        cam, D, model = camera_from_info(info, self._where(self.topics.info))
        if (cam.width, cam.height) != size:
            raise InputError(f"{self._where(self.topics.info)}: camera_info is {cam.width}x{cam.height} but the "
                             f"colour images are {size[0]}x{size[1]}")
        if np.any(np.abs(D) > 1e-9):
            if not undistort:
                raise InputError(f"{self._where(self.topics.info)}: images are distorted ({model}, D={D.tolist()}); "
                                 "expected rectified images, or undistortion on")
            self._maps = _undistort_maps(cam, D, model, self._where(self.topics.info))
        return cam

    def _poses(self, rows, max_diff) -> np.ndarray | None:
        if not rows:
            return None
        rows = sorted(rows, key=lambda r: r[0])
        stamps = np.array([r[0] for r in rows])
        return poses_at(self._t, stamps, np.stack([r[1] for r in rows]), max_diff)

    # ---- frames -------------------------------------------------------------------------------------------

    def _keys(self, i: int) -> list[tuple[str, int]]:
        keys = [(self.topics.color, int(self._color_rec[i]))]
        if self._depth_conn is not None:
            keys.append((self.topics.depth, int(self._depth_rec[i])))
        return keys

    def _messages(self, i: int) -> dict[str, tuple[object, bytes]]:
        keys = self._keys(i)
        if self._stream is None or self._stream[1] != i:
            start = min(k[1] for k in keys)
            conns = [c for c in (self._color_conn, self._depth_conn) if c is not None]
            self._stream = [self._reader.messages(connections=conns, start=start), i]
            self._stash.clear()
        gen = self._stream[0]
        later = {k for j in range(i + 1, min(i + 1 + _AHEAD, len(self))) for k in self._keys(j)}
        while not all(k in self._stash for k in keys):
            try:
                conn, rec, raw = next(gen)
            except StopIteration:
                raise InputError(f"{self.root}: frame {i} is indexed but its messages cannot be read") from None
            except Exception as e:  # noqa: BLE001 - read from frame i's record time, a damaged bag can fail where
                # the index's pass did not (an SQLite page only that query reaches): rosbags' and apsw's errors
                raise InputError(f"{self.root}: frame {i} is indexed but its messages cannot be read ({why(e)}); "
                                 "expected an undamaged bag") from None
            key = (conn.topic, int(rec))
            if key in keys or (key in later and len(self._stash) < 2 * _AHEAD):
                self._stash[key] = (conn, raw)
        self._stream[1] = i + 1
        return {k[0]: self._stash.pop(k) for k in keys}

    def __getitem__(self, i: int) -> Frame:
        i = self._checked_index(i)
        msgs = self._messages(i)
        conn, raw = msgs[self.topics.color]
        color = decode_color(self._deserialize(conn, raw, i), conn.msgtype, self._where(conn.topic))
        self._check_size(color, self.topics.color)
        depth = None
        if self._depth_conn is not None:
            conn, raw = msgs[self.topics.depth]
            depth = decode_depth(self._deserialize(conn, raw, i), conn.msgtype, self._where(conn.topic))
            self._check_size(depth, self.topics.depth)
        if self._maps is not None:
            color, depth = _remap(self._maps, color, depth)
        return Frame(index=int(i), timestamp=float(self._t[i]), color=color, depth=depth,
                     T_world_cam_gt=_row(self._gt, i), T_world_cam_odom=_row(self._odom, i))

    def _deserialize(self, conn, raw, i: int):
        try:
            return self._reader.deserialize(raw, conn.msgtype)
        except Exception as e:  # noqa: BLE001 - as _messages: what a damaged bag's other read path returns
            raise InputError(f"{self._where(conn.topic)}: frame {i}'s message does not deserialise as "
                             f"{conn.msgtype} ({why(e)})") from None

    def _check_size(self, img: np.ndarray, topic: str) -> None:
        if img.shape[:2] != (self.camera.height, self.camera.width):
            raise InputError(f"{self._where(topic)}: image is {img.shape[1]}x{img.shape[0]}, expected "
                             f"{self.camera.width}x{self.camera.height} (camera_info)")

    @property
    def is_rgbd(self) -> bool:
        return self._depth_conn is not None

    def close(self) -> None:
        if self._reader is not None:
            self._stream = None
            self._reader.close()
            self._reader = None

    def __repr__(self) -> str:
        kind = "rgbd" if self.is_rgbd else "mono"
        return (f"BagSequence({self.name!r}, {len(self)} {kind} frames, {self.camera.width}x{self.camera.height}, "
                f"{self.root}, color={self.topics.color})")


def _undistort_maps(cam: PinholeCamera, D: np.ndarray, model: str, where: str):
    import cv2

    K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]], dtype=np.float64)
    size = (cam.width, cam.height)
    if model in ("plumb_bob", "rational_polynomial", "equidistant", "") and not np.all(np.isfinite(D)):
        raise InputError(f"{where}: distortion coefficients D={D.tolist()[:14]} are not finite")
    if model in ("plumb_bob", "rational_polynomial", ""):
        if D.size not in (4, 5, 8, 12, 14):
            raise InputError(f"{where}: {D.size} distortion coefficients for {model or 'plumb_bob'!r}; expected 4, "
                             "5, 8, 12 or 14 (OpenCV's k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tx ty]]]])")
        return _maps_or_error(lambda: cv2.initUndistortRectifyMap(K, D, None, K, size, cv2.CV_32FC1), K, D, where)
    if model == "equidistant":
        if D.size < 4:
            raise InputError(f"{where}: {D.size} distortion coefficients for 'equidistant'; expected 4 (k1..k4)")
        return _maps_or_error(lambda: cv2.fisheye.initUndistortRectifyMap(K, D[:4], np.eye(3), K, size,
                                                                          cv2.CV_32FC1), K, D, where)
    raise InputError(f"{where}: distortion model {model!r} is not supported; expected plumb_bob, "
                     "rational_polynomial or equidistant, or rectified images")


def _maps_or_error(make, K: np.ndarray, D: np.ndarray, where: str):
    import cv2

    try:
        return make()
    except cv2.error as e:  # e.g. a K that is singular in floating point (fx of 1e-300)
        raise InputError(f"{where}: camera_info's K={K.reshape(-1).tolist()} and D={D.tolist()[:14]} do not make an "
                         f"undistortion ({why(e)}); expected a camera's intrinsics") from None


def _remap(maps, color: np.ndarray, depth: np.ndarray | None):
    """Undistorted colour (bilinear) and depth (nearest: depth is never blended across an edge), same K."""
    import cv2

    color = cv2.remap(color, maps[0], maps[1], cv2.INTER_LINEAR)
    if depth is not None:
        depth = cv2.remap(depth, maps[0], maps[1], cv2.INTER_NEAREST)
    return color, depth
