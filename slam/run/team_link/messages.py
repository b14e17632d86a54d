"""What a GRAND-SLAM agent and its team server send each other across processes: versioned messages in the
swarm's safe binary form (slam.flocc.swarm.messages: header, JSON scalars, typed arrays; no pickle), with their
own magic so the two families never mix.

Agent -> server (each carries `mid`, the agent's message id; the server acknowledges ids and keeps what it has
by id, so duplicates and reordering change nothing):

  Join           the agent's name, camera and config digest, sent until the server welcomes it
  KeyframeMeta   one keyframe: pose in its submap, the round it was made in, descriptor, the tracking edge from the
                 previous keyframe with its information, and (a submap's first keyframe) the new submap's origin
                 relative to the previous one
  KeyframeImage  the keyframe's images (slam.run.team_link.images): the loop-closure copy, and the
                 mapping-resolution copy when the server refines the merged map on it, losslessly or each picture
                 once (JPEG colour, inverse-depth steps); sent once
  Frames         tracked poses of every frame since the last batch, the rounds done and keyframes made so far
  SubmapData     a finished submap's Gaussians (local frame; float32, float16 for all but the means, or the
                 link form of slam.dense.submap_codec, without those the server's overlap cull drops anyway:
                 slam.dense.team.link_cull)
  Done           the agent's totals after its last frame (times, skipped frames, its own byte counts)

Server -> agent: Welcome, Ack (message ids received), Correction (each submap's new origin in the agent's world
frame, after an optimisation), Finished (the run's results are written).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import torch

from swarmsplat.slam.dense.submap_codec import CodecError, CodecSpec, decode, encode, for_link, stored_compact
from swarmsplat.slam.flocc.swarm.messages import Codec, Message, MessageError, _check_poses

MAGIC = b"GSLK"
SCHEMA_VERSION = 3  # 2: SubmapData's compact form (blob); 3: its link form, KeyframeImage's depth forms
SERVER = 0  # the server's node id; agent k is node k + 1


def _finite_poses(T: np.ndarray, what: str) -> None:
    """MessageError unless T [N, 4, 4] is finite with the last row 0 0 0 1 (tracked poses: their rotations are
    the tracker's, orthonormal to its rounding, and are passed on as they are)."""
    if T.ndim != 3 or T.shape[1:] != (4, 4) or not np.all(np.isfinite(T)) or \
            (len(T) and np.abs(T[:, 3] - [0, 0, 0, 1]).max() > 0):
        raise MessageError(f"{what}: poses must be finite [N, 4, 4] with a last row 0 0 0 1")


def _f(shape_tail=()):
    return lambda: np.zeros((0, *shape_tail))


def _i():
    return np.zeros(0, np.int64)


def _u8():
    return np.zeros(0, np.uint8)


@dataclass
class Join(Message):
    TYPE: ClassVar[int] = 1
    SCALARS: ClassVar[dict] = {"mid": int, "name": str, "camera": list, "config": str, "rounds": int}
    mid: int = 0
    name: str = ""
    camera: list = field(default_factory=list)  # [fx, fy, cx, cy, width, height] of the input frames
    config: str = ""  # digest of the agent's config tree (the server checks it against its own)
    rounds: int = 0  # input frames it will read (0: unknown, e.g. live)

    def validate(self) -> None:
        if not self.name or len(self.camera) != 6 or not all(isinstance(c, (int, float)) and c > 0
                                                             for c in self.camera):
            raise MessageError("Join: a name and 6 positive camera numbers expected")


@dataclass
class KeyframeMeta(Message):
    TYPE: ClassVar[int] = 2
    SCALARS: ClassVar[dict] = {"mid": int, "id": int, "frame_index": int, "timestamp": float, "submap_id": int,
                               "round": int}
    ARRAYS: ClassVar[dict] = {"T_local_cam": ("<f8", 3), "descriptor": ("<f4", 1), "odom_T": ("<f8", 3),
                              "odom_info": ("<f8", 3), "submap_start": ("<f8", 3), "exposure": ("<f8", 1)}
    mid: int = 0
    id: int = 0
    frame_index: int = 0
    timestamp: float = 0.0
    submap_id: int = 0
    round: int = 0
    T_local_cam: np.ndarray = field(default_factory=_f((4, 4)))  # [1, 4, 4]
    descriptor: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))  # [D] or [0]: none
    odom_T: np.ndarray = field(default_factory=_f((4, 4)))  # [1, 4, 4] previous keyframe -> this one, or [0]
    odom_info: np.ndarray = field(default_factory=_f((6, 6)))  # [1, 6, 6] or [0]
    submap_start: np.ndarray = field(default_factory=_f((4, 4)))  # [1, 4, 4] T_prev_local_new, or [0]
    # [6] the exposure fitted when the keyframe was made (slam.dense.mapping.exposure), or [0]: no model
    exposure: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def validate(self) -> None:
        _finite_poses(self.T_local_cam, "KeyframeMeta")
        _finite_poses(self.odom_T, "KeyframeMeta")
        _finite_poses(self.submap_start, "KeyframeMeta")
        if len(self.T_local_cam) != 1 or len(self.odom_T) != len(self.odom_info) or len(self.odom_T) > 1 \
                or len(self.submap_start) > 1 or self.odom_info.shape[1:] != (6, 6) \
                or not np.all(np.isfinite(self.odom_info)) or not np.all(np.isfinite(self.descriptor)) \
                or len(self.exposure) not in (0, 6) or not np.all(np.isfinite(self.exposure)):
            raise MessageError("KeyframeMeta: one pose, at most one finite edge and submap start, and 0 or 6 "
                               "finite exposure numbers expected")
        if min(self.id, self.frame_index, self.submap_id, self.round) < 0 or (self.id > 0) != (len(self.odom_T) == 1):
            raise MessageError("KeyframeMeta: negative ids, or an edge missing / given for the first keyframe")


@dataclass
class KeyframeImage(Message):
    TYPE: ClassVar[int] = 3
    SCALARS: ClassVar[dict] = {"mid": int, "id": int, "small_camera": list, "map_camera": list,
                               "depth_form": list, "inverse_depth_k": float}
    ARRAYS: ClassVar[dict] = {"small_color": ("|u1", 1), "small_depth": ("|u1", 1), "map_color": ("|u1", 1),
                              "map_depth": ("|u1", 1)}
    mid: int = 0
    id: int = 0
    small_camera: list = field(default_factory=list)  # [fx, fy, cx, cy, width, height]
    map_camera: list = field(default_factory=list)  # [] when the mapping-resolution copy is not sent
    # per copy (slam.run.team_link.images): 0 = depth PNG of float32 bits, 1 = in millimetres, 2 = in inverse-depth
    # steps (round(inverse_depth_k / z)), 3 = made from the other copy's
    depth_form: list = field(default_factory=list)
    inverse_depth_k: float = 0.0  # metres
    small_color: np.ndarray = field(default_factory=_u8)  # PNG or JPEG bytes; empty: made from the other copy's
    small_depth: np.ndarray = field(default_factory=_u8)
    map_color: np.ndarray = field(default_factory=_u8)
    map_depth: np.ndarray = field(default_factory=_u8)

    def validate(self) -> None:
        two = len(self.map_camera) == 6
        if len(self.small_camera) != 6 or len(self.map_camera) not in (0, 6) or self.id < 0 \
                or len(self.depth_form) != 1 + two or not all(f in (0, 1, 2, 3) for f in self.depth_form):
            raise MessageError("KeyframeImage: cameras and depth forms do not match the copies sent")
        if self.depth_form[0] == 2:  # each picture once: small depth, the colour of the largest copy
            if not (self.inverse_depth_k > 0 and len(self.small_depth) and len(self.map_color if two else
                                                                                self.small_color)
                    and self.depth_form[1:] in ([], [3])):
                raise MessageError("KeyframeImage: inverse-depth images need k > 0, the small depth and one colour")
        elif 3 in self.depth_form or not (len(self.small_color) and len(self.small_depth)) \
                or (two and not (len(self.map_color) and len(self.map_depth))):
            raise MessageError("KeyframeImage: lossless images need every copy's colour and depth")


@dataclass
class Frames(Message):
    TYPE: ClassVar[int] = 4
    SCALARS: ClassVar[dict] = {"mid": int, "rounds_done": int, "keyframes": int, "skipped": list, "dropped": list}
    ARRAYS: ClassVar[dict] = {"frame_index": ("<i8", 1), "timestamp": ("<f8", 1), "submap_id": ("<i8", 1),
                              "T_local_cam": ("<f8", 3)}
    mid: int = 0
    rounds_done: int = 0  # input rounds the agent has finished (frames read, tracked or skipped)
    keyframes: int = 0  # keyframes it had made by then
    skipped: list = field(default_factory=list)  # [[frame index, reason]] skipped in this batch
    dropped: list = field(default_factory=list)  # keyframe ids whose images the agent's queue dropped
    frame_index: np.ndarray = field(default_factory=_i)
    timestamp: np.ndarray = field(default_factory=lambda: np.zeros(0))
    submap_id: np.ndarray = field(default_factory=_i)
    T_local_cam: np.ndarray = field(default_factory=_f((4, 4)))

    def validate(self) -> None:
        n = len(self.frame_index)
        if len(self.timestamp) != n or len(self.submap_id) != n or len(self.T_local_cam) != n \
                or min(self.rounds_done, self.keyframes) < 0:
            raise MessageError("Frames: arrays of different lengths or negative counts")
        _finite_poses(self.T_local_cam, "Frames")
        if not all(isinstance(s, list) and len(s) == 2 and isinstance(s[0], int) and isinstance(s[1], str)
                   for s in self.skipped):
            raise MessageError("Frames: skipped must be [[frame index, reason]]")
        if not all(isinstance(k, int) and k >= 0 for k in self.dropped):
            raise MessageError("Frames: dropped must be keyframe ids")


@dataclass
class SubmapData(Message):
    TYPE: ClassVar[int] = 5
    SCALARS: ClassVar[dict] = {"mid": int, "id": int, "keyframe_ids": list}
    ARRAYS: ClassVar[dict] = {"means": ("<f4", 2), "rest32": ("<f4", 2), "rest16": ("<f2", 2), "blob": ("|u1", 1)}
    mid: int = 0
    id: int = 0
    keyframe_ids: list = field(default_factory=list)
    means: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))  # [N, 3] local frame
    rest32: np.ndarray = field(default_factory=lambda: np.zeros((0, 11), np.float32))  # [N, 11] or [0, 11]
    rest16: np.ndarray = field(default_factory=lambda: np.zeros((0, 11), np.float16))  # [0, 11] or [N, 11]
    blob: np.ndarray = field(default_factory=_u8)  # the compact form (slam.dense.submap_codec), or empty

    def validate(self) -> None:
        if len(self.blob):
            if len(self.means) or len(self.rest32) or len(self.rest16) or self.id < 0:
                raise MessageError("SubmapData: the compact form alone expected")
            try:  # decoded here to refuse a corrupt one on arrival; the receiver keeps the bytes
                decode(self.blob.tobytes(), source="SubmapData")
            except CodecError as e:
                raise MessageError(str(e)) from None
            return
        n = len(self.means)
        rest = self.rest32 if len(self.rest32) else self.rest16
        if self.means.shape[1:] != (3,) or rest.shape[1:] != (11,) or len(rest) != n \
                or (len(self.rest32) and len(self.rest16)) or self.id < 0:
            raise MessageError("SubmapData: means [N, 3] and one parameter block [N, 11] expected")
        if not (np.all(np.isfinite(self.means)) and np.all(np.isfinite(rest))):
            raise MessageError("SubmapData: non-finite Gaussian parameters")

    @classmethod
    def pack(cls, mid: int, submap, encoding: str, keep=None, mean_bits: int = 16) -> "SubmapData":
        """A finished submap (slam.dense.gaussian_map.Submap) on the link; encoding 'float32', 'float16' or
        'compact' (the link form of the values the agent stores it as, when it stores it compact, with means of
        `mean_bits`). keep: [N] bool, the Gaussians to send (None: all)."""
        head = dict(mid=mid, id=submap.id, keyframe_ids=[int(k) for k in submap.keyframe_ids])
        if encoding == "compact":
            blob = stored_compact(submap)
            if blob is None:
                blob = encode(submap.params, CodecSpec())
            return cls(**head, blob=np.frombuffer(for_link(blob, keep, mean_bits=mean_bits), np.uint8))
        p = submap.params.detached()
        if keep is not None:
            p = p.select(torch.as_tensor(np.asarray(keep, dtype=bool)))
        rest = torch.cat([p.log_scales, p.quats, p.logit_opacities[:, None], p.colors], 1).cpu().numpy()
        half = encoding == "float16"
        return cls(**head, means=p.means.cpu().numpy().astype(np.float32),
                   rest32=np.zeros((0, 11), np.float32) if half else rest.astype(np.float32),
                   rest16=rest.astype(np.float16) if half else np.zeros((0, 11), np.float16))

    def params(self):
        """The Gaussians as slam.dense.gaussian_map.GaussianParams (float32)."""
        from swarmsplat.slam.dense.gaussian_map import GaussianParams

        if len(self.blob):
            return decode(self.blob.tobytes(), source="SubmapData")
        rest = torch.from_numpy((self.rest32 if len(self.rest32) else self.rest16).astype(np.float32))
        return GaussianParams(torch.from_numpy(self.means.astype(np.float32)), rest[:, 0:3].contiguous(),
                              rest[:, 3:7].contiguous(), rest[:, 7].contiguous(), rest[:, 8:11].contiguous())


@dataclass
class Done(Message):
    TYPE: ClassVar[int] = 6
    SCALARS: ClassVar[dict] = {"mid": int, "rounds": int, "keyframes": int, "submaps": int, "tracking_s": float,
                               "mapping_s": float, "frames": int, "non_finite_dropped": int, "link": dict,
                               "status": str}
    mid: int = 0
    rounds: int = 0
    keyframes: int = 0
    submaps: int = 0
    tracking_s: float = 0.0
    mapping_s: float = 0.0
    frames: int = 0  # frames tracked
    non_finite_dropped: int = 0
    link: dict = field(default_factory=dict)  # the agent's own queue statistics (resends, dropped images)
    status: str = "complete"


@dataclass
class Welcome(Message):
    TYPE: ClassVar[int] = 7
    SCALARS: ClassVar[dict] = {"agent": int, "ok": int, "reason": str}
    agent: int = 0
    ok: int = 1
    reason: str = ""


@dataclass
class Ack(Message):
    TYPE: ClassVar[int] = 8
    ARRAYS: ClassVar[dict] = {"mids": ("<i8", 1)}
    mids: np.ndarray = field(default_factory=_i)


@dataclass
class Correction(Message):
    TYPE: ClassVar[int] = 9
    SCALARS: ClassVar[dict] = {"stamp": int}
    ARRAYS: ClassVar[dict] = {"submap_ids": ("<i8", 1), "T_world_local": ("<f8", 3), "T_global_world": ("<f8", 3)}
    stamp: int = 0  # the server's optimisation count: a newer correction has a greater stamp
    submap_ids: np.ndarray = field(default_factory=_i)
    T_world_local: np.ndarray = field(default_factory=_f((4, 4)))  # [S, 4, 4] in the agent's own world frame
    T_global_world: np.ndarray = field(default_factory=_f((4, 4)))  # [1, 4, 4] its world in the team's frame

    def validate(self) -> None:
        _check_poses(self.T_world_local, "Correction")
        _check_poses(self.T_global_world, "Correction")
        if len(self.submap_ids) != len(self.T_world_local) or len(self.T_global_world) != 1:
            raise MessageError("Correction: one origin per submap id and one agent frame expected")


@dataclass
class Finished(Message):
    TYPE: ClassVar[int] = 10
    SCALARS: ClassVar[dict] = {"status": str}
    status: str = "complete"


LINK = Codec(MAGIC, SCHEMA_VERSION, {c.TYPE: c for c in (Join, KeyframeMeta, KeyframeImage, Frames, SubmapData,
                                                         Done, Welcome, Ack, Correction, Finished)})

AGENT_KINDS = ("Join", "KeyframeMeta", "KeyframeImage", "Frames", "SubmapData", "Done")
