"""A team agent in its own process: it tracks and maps its sequence as an agent of the in-process team does, and
sends the server what it needs (slam.run.team_link.messages) through an `Outbox` that keeps every message until
the server acknowledges it. A lost link changes nothing on the agent's side: it keeps tracking and mapping,
queues, and sends again when the server answers; when its queue passes `link.queue_mb` the oldest keyframe
images are dropped first (their poses and edges never are).
"""

from __future__ import annotations

import os
import sys
import time
from collections import OrderedDict

import numpy as np

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import SwarmsplatError

from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.dense.agent import Agent
from swarmsplat.slam.dense.team.link_cull import sent_gaussians
from swarmsplat.slam.run.guard import read_frame

from . import messages as L
from .images import camera_list, encode_images


def config_digest(cfg: SlamConfig) -> str:
    """What the agent and the server must agree on: every section but the link's own and the kernels'."""
    import hashlib

    d = cfg.model_dump(mode="json")
    for k in ("link", "kernels", "runtime", "checkpoint", "demo"):
        d.pop(k, None)
    return hashlib.sha1(repr(sorted(d.items())).encode()).hexdigest()[:12]


def agent_config(cfg: SlamConfig) -> SlamConfig:
    """A team agent's pipeline settings: its own loop optimisation is off (the server optimises), as in
    slam.run.team.Team."""
    return cfg.override({"loop_closure": {"enabled": False}})


def server_needs_map_views(cfg: SlamConfig) -> bool:
    rc = cfg.map_refine
    return rc.views == "mapping" and rc.iterations_per_keyframe > 0 and rc.max_iterations > 0


class LinkAgent(Agent):
    """An Agent that remembers, for each submap it starts, the tracked pose it started at in the previous one (the
    new origin relative to the previous origin, which the server composes with its own corrected origins)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.submap_starts: dict[int, np.ndarray] = {}

    def _maybe_start_submap(self, T_local_cam: np.ndarray) -> np.ndarray:
        n = len(self.gmap.submaps)
        T = np.array(T_local_cam, dtype=np.float64)
        out = super()._maybe_start_submap(T_local_cam)
        if len(self.gmap.submaps) > n and n > 0:
            self.submap_starts[n] = T
        return out


class Outbox:
    """An agent's messages until acknowledged: `put` sends and keeps, `ack` forgets, `resend` sends again what
    waited longer than link.resend_s. Keyframe images beyond link.queue_mb are dropped, oldest first."""

    def __init__(self, tx, link, clock=time.monotonic):
        self.tx, self.link, self.clock = tx, link, clock
        self.items: OrderedDict[int, list] = OrderedDict()  # mid -> [message, last sent]
        self.mid = 0
        self.resent = 0
        self.dropped_images: list[int] = []  # keyframe ids whose images were dropped
        self._new_drops: list[int] = []

    def next_mid(self) -> int:
        self.mid += 1
        return self.mid

    def put(self, msg: L.Message) -> None:
        self.items[msg.mid] = [msg, self.clock()]
        self.tx.send(L.SERVER, msg)
        self._bound()

    def ack(self, mids) -> None:
        for m in np.asarray(mids).tolist():
            self.items.pop(int(m), None)

    def resend(self) -> int:
        now, n = self.clock(), 0
        for item in self.items.values():
            if now - item[1] >= self.link.resend_s:
                self.tx.send(L.SERVER, item[0])
                item[1] = now
                n += 1
        self.resent += n
        return n

    def take_drops(self) -> list[int]:
        out, self._new_drops = self._new_drops, []
        return out

    def image_bytes(self) -> int:
        return sum(_image_nbytes(it[0]) for it in self.items.values() if isinstance(it[0], L.KeyframeImage))

    def _bound(self) -> None:
        limit = self.link.queue_mb * 1e6
        total = self.image_bytes()
        for mid in [m for m, it in self.items.items() if isinstance(it[0], L.KeyframeImage)]:
            if total <= limit:
                break
            msg = self.items.pop(mid)[0]
            total -= _image_nbytes(msg)
            self.dropped_images.append(msg.id)
            self._new_drops.append(msg.id)

    def stats(self) -> dict:
        return {"resent": self.resent, "dropped_images": len(self.dropped_images), "queued": len(self.items)}

    def __getstate__(self) -> dict:  # a checkpoint keeps the queue, not the transport
        return {**self.__dict__, "tx": None}

    def reattach(self, tx, first_mid: int) -> None:
        """After a resume: send on `tx`, number new messages from `first_mid` on (ids the killed process may have
        used after the checkpoint, for other content, stay unused) and send what waits at the next `resend`."""
        self.tx, self.mid = tx, max(self.mid, int(first_mid))
        for item in self.items.values():
            item[1] = float("-inf")


def _image_nbytes(m: L.KeyframeImage) -> int:
    return int(m.small_color.nbytes + m.small_depth.nbytes + m.map_color.nbytes + m.map_depth.nbytes)


class AgentNode:
    """One team agent and its link: `join`, then `step_round` per input round, then `finish`."""

    def __init__(self, camera: PinholeCamera, cfg: SlamConfig, name: str, tx, clock=time.monotonic):
        self.cfg, self.name, self.tx = cfg, name, tx
        self.agent = LinkAgent(camera, agent_config(cfg), name=name)
        # as an agent of the in-process team (slam.run.team.Team): what it keeps is what its later steps may read
        self.agent.keep_keyframe_images = server_needs_map_views(cfg)
        self.outbox = Outbox(tx, cfg.link, clock)
        self._join_msg = None
        self.map_views = server_needs_map_views(cfg)
        self.welcomed = False
        self.finished_by_server = False
        self.corrections = 0
        self._sent_frames = 0  # agent.poses already sent
        self._sent_skips = 0
        self._sent_submaps = 0
        self.journal = None  # slam.run.checkpoint.PoseJournal of an agent given an output folder
        self.parent = None  # pid of the process that started this one and must outlive it (run --processes)

    def __getstate__(self) -> dict:  # what a checkpoint keeps (slam.run.team_link.member): no transport, no file
        return {**self.__dict__, "tx": None, "journal": None, "parent": None, "welcomed": False,
                "finished_by_server": False}

    def reattach(self, tx, journal, first_mid: int) -> None:
        """A node loaded from a checkpoint, on a new transport and its resumed journal (Outbox.reattach)."""
        self.tx, self.journal = tx, journal
        self.outbox.reattach(tx, first_mid)

    # ---- the link ----------------------------------------------------------------------------------------------

    def start(self, rounds: int) -> None:
        """Ask to join (the Join stays queued until the server acknowledges it)."""
        self._join_msg = L.Join(mid=self.outbox.next_mid(), name=self.name, camera=camera_list(self.agent.camera),
                                config=config_digest(self.cfg), rounds=int(rounds))
        self.outbox.put(self._join_msg)

    def join(self, rounds: int, timeout: float, *, say=print) -> None:
        """Send Join until the server welcomes this agent; SwarmsplatError after `timeout` seconds."""
        self.start(rounds)
        msg = self._join_msg
        t0 = last = time.monotonic()
        while not self.welcomed:
            self.service()
            now = time.monotonic()
            if now - t0 > timeout:
                raise SwarmsplatError(f"{self.name}: no team server answered within {timeout:.0f} s "
                                      f"(link.connect_timeout_s); is `swarmsplat server` running and reachable?")
            if now - last > 1.0:
                self.tx.send(L.SERVER, msg)
                last = now
                if int(now - t0) % 5 == 0:
                    say(f"{self.name}: waiting for the team server ({now - t0:.0f} s)", file=sys.stderr)
            time.sleep(0.05)

    def service(self) -> None:
        """Read what the server sent (welcome, acknowledgements, corrections, the end) and send again what waited."""
        if self.parent is not None and os.getppid() != self.parent:  # its run was killed: a resumed one takes over
            raise SwarmsplatError(f"{self.name}: the run that started this agent process has ended")
        for h, msg in self.tx.poll():
            if h.sender != L.SERVER:
                continue
            if isinstance(msg, L.Welcome):
                if not msg.ok:
                    raise SwarmsplatError(f"{self.name}: the team server refused this agent: {msg.reason}")
                self.welcomed = True
            elif isinstance(msg, L.Ack):
                self.outbox.ack(msg.mids)
            elif isinstance(msg, L.Correction):
                self._correct(msg)
            elif isinstance(msg, L.Finished):
                self.finished_by_server = True
        self.outbox.resend()

    def _correct(self, msg: L.Correction) -> None:
        """The server's latest submap origins (this agent's world frame): its own map and trajectory follow them."""
        if msg.stamp <= self.corrections:
            return
        self.corrections = msg.stamp
        sms = self.agent.gmap.submaps
        for sid, T in zip(msg.submap_ids.tolist(), msg.T_world_local):
            if sid < len(sms):
                self.agent.gmap.place_submap(sms[sid], T)

    # ---- the agent ------------------------------------------------------------------------------------------

    def step_round(self, seq, i: int, stride: int, strict: bool = False) -> None:
        """Round i: frame i * stride of `seq` (skipped with a warning when unreadable), then what it produced."""
        self.step_frame(read_frame(seq, i * stride, self.agent, strict=strict), i)

    def step_frame(self, f, i: int):
        """Round i on frame `f` (a slam.io.datasets Frame; None: nothing to track this round), then send what it
        produced. Returns the frame's pose record (None when it was not tracked)."""
        ag = self.agent
        n_kf, n_sm = len(ag.keyframes), len(ag.gmap.submaps)
        rec = ag.step(f.index, f.timestamp, f.color, f.depth) if f is not None else None
        if self.journal is not None:
            self.journal.follow(ag)
        if len(ag.gmap.submaps) > n_sm and n_sm > 0:
            self._send_submaps(n_sm - self.cfg.link.submap_delay)
        if len(ag.keyframes) > n_kf:
            self._send_keyframe(ag.keyframes[-1], i)
        self._send_frames(i + 1)
        self.service()
        return rec

    def _send_keyframe(self, kf, round_: int) -> None:
        ag = self.agent
        odom = ag.loops.odometry[-1] if kf.id > 0 else None
        start = ag.submap_starts.get(kf.submap_id) if kf.submap_id > 0 and \
            ag.gmap.submaps[kf.submap_id].keyframe_ids[0] == kf.id else None
        e = lambda n: np.zeros((0, n, n))  # noqa: E731
        self.outbox.put(L.KeyframeMeta(
            mid=self.outbox.next_mid(), id=kf.id, frame_index=int(kf.frame_index), timestamp=float(kf.timestamp),
            submap_id=kf.submap_id, round=int(round_), T_local_cam=kf.T_local_cam[None],
            descriptor=np.zeros(0, np.float32) if kf.descriptor is None else np.asarray(kf.descriptor, np.float32),
            odom_T=e(4) if odom is None else odom.T_ij[None], odom_info=e(6) if odom is None else odom.info[None],
            submap_start=e(4) if start is None else start[None],
            exposure=np.zeros(0) if kf.exposure_prior is None else np.asarray(kf.exposure_prior, np.float64)))
        link = self.cfg.link
        big = kf.map_rgbd if self.map_views and link.map_views else None
        self.outbox.put(L.KeyframeImage(mid=self.outbox.next_mid(), id=kf.id, **encode_images(kf.small, big, link)))

    def _send_submaps(self, upto: int) -> None:
        """The finished submaps with ids below `upto` not sent yet, each without the Gaussians the server's
        overlap cull drops anyway (link.cull_gaussians), judged with every keyframe the agent has made by then:
        link.submap_delay later submaps' keyframes see much of a submap again."""
        for sid in range(self._sent_submaps, min(upto, len(self.agent.gmap.submaps))):
            sm = self.agent.gmap.submaps[sid]
            keep = sent_gaussians(self.agent, sid) if self.cfg.link.cull_gaussians else None
            self.outbox.put(L.SubmapData.pack(self.outbox.next_mid(), sm, self.cfg.link.gaussians, keep,
                                              self.cfg.link.mean_bits))
            self._sent_submaps = sid + 1

    def _send_frames(self, rounds_done: int) -> None:
        ag = self.agent
        recs = ag.poses[self._sent_frames:]
        skips = ag.skipped_frames()[self._sent_skips:]
        self._sent_frames, self._sent_skips = len(ag.poses), len(ag.time.skipped)
        drops = self.outbox.take_drops()
        self.outbox.put(L.Frames(
            mid=self.outbox.next_mid(), rounds_done=int(rounds_done), keyframes=len(ag.keyframes),
            skipped=[[int(s["frame"]), str(s["reason"])] for s in skips], dropped=[int(k) for k in drops],
            frame_index=np.array([r.frame_index for r in recs], np.int64),
            timestamp=np.array([r.timestamp for r in recs], np.float64),
            submap_id=np.array([r.submap_id for r in recs], np.int64),
            T_local_cam=np.stack([r.T_local_cam for r in recs]) if recs else np.zeros((0, 4, 4))))

    def send_last(self, rounds: int, status: str = "complete") -> None:
        """After the last round: the submaps not sent yet (the last one too), the last poses and the totals."""
        ag = self.agent
        self._send_submaps(len(ag.gmap.submaps))
        self._send_frames(rounds)
        t = ag.time
        self.outbox.put(L.Done(mid=self.outbox.next_mid(), rounds=int(rounds), keyframes=len(ag.keyframes),
                               submaps=len(ag.gmap.submaps), tracking_s=float(t.tracking), mapping_s=float(t.mapping),
                               frames=int(t.frames), non_finite_dropped=int(ag.mapper.non_finite_dropped),
                               link={**self.outbox.stats(), "bytes": self.tx.stats.to_dict()}, status=status))

    def settled(self) -> bool:
        """Everything acknowledged, or the server has written the results."""
        return not self.outbox.items or self.finished_by_server

    def finish(self, rounds: int, timeout: float, status: str = "complete") -> bool:
        """`send_last`, then wait (at most `timeout` s) until the server has acknowledged everything. Returns True
        when it has."""
        self.send_last(rounds, status)
        t_end = time.monotonic() + timeout
        while not self.settled() and time.monotonic() < t_end:
            self.service()
            time.sleep(0.05)
        return self.settled()
