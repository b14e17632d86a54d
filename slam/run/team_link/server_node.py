"""The team server in its own process: it mirrors every agent from its messages (slam.dense.team.mirror) and runs
the same Server as the in-process team on them.

Order. The in-process team hands the server agent a's keyframe of round r right after agent a's step of round r,
agents in index order. The node keeps that order whatever the link does: keyframe (r, a) is handed over once every
other agent b has reported all its keyframes of the rounds before it (b < a: rounds <= r; b > a: rounds < r), or
has finished, or is lost, and every earlier keyframe in that order has been handed over (one whose images have not
arrived yet holds back the later ones, though its agent has reported later rounds). So the server sees the same keyframes in the same order and makes the same decisions
as in one process, however the agents' processes interleave. An agent on live topics joins without a frame count
(Join rounds 0): nobody waits for it (its rounds are its frames, which come at the camera's pace), and its
keyframes go to the server as they arrive and the recorded agents' rounds allow.

Faults. Messages are kept by id (a duplicate or a late copy changes nothing) and acknowledged; every new message
is appended to `link/journal.bin` in the output folder, and fsync'd, before it is acknowledged, so a server
restarted on the same folder replays the journal, is back in the state it had, and continues with the agents'
resent messages (a record a kill cut short is dropped from the file: it was not acknowledged).
An agent silent for link.agent_timeout_s is reported lost and the others go on without it.
"""

from __future__ import annotations

import os
import struct
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.slam.dense.agent import FramePose
from swarmsplat.slam.dense.frames import RGBD
from swarmsplat.slam.dense.team.held import held_bytes
from swarmsplat.slam.flocc.swarm.messages import MessageError

from . import messages as L
from .agent_node import config_digest
from .images import decode_images

RGBD_BYTES_PER_PIXEL = 3 + 2  # a raw RGB-D frame: 8-bit RGB + 16-bit depth
REFERENCE_KEYFRAME_BYTES = 640 * 480 * RGBD_BYTES_PER_PIXEL  # a 640x480 one, the size most RGB-D cameras give


def raw_keyframe_bytes(camera: list) -> int:
    """Bytes of one raw RGB-D frame at the size of an agent's input frames (its Join camera [fx, fy, cx, cy, width,
    height]): what sending its keyframes uncompressed would take."""
    return int(camera[4]) * int(camera[5]) * RGBD_BYTES_PER_PIXEL


def _camera(c: list) -> PinholeCamera:
    return PinholeCamera(float(c[0]), float(c[1]), float(c[2]), float(c[3]), int(c[4]), int(c[5]))


@dataclass
class Peer:
    """What the server has from one agent."""

    name: str
    joined: bool = False
    seen: set = field(default_factory=set)  # message ids received
    meta: dict = field(default_factory=dict)  # keyframe id -> KeyframeMeta
    images: dict = field(default_factory=dict)  # keyframe id -> KeyframeImage
    dropped: set = field(default_factory=set)  # keyframe ids whose images the agent dropped
    submaps: dict = field(default_factory=dict)  # submap id -> SubmapData
    installed: set = field(default_factory=set)  # submap ids whose Gaussians are in the agent's mirror
    claims: list = field(default_factory=list)  # (rounds done, keyframes made by then), from Frames
    rounds_done: int = 0  # rounds whose keyframes have all arrived
    open_ended: bool = False  # joined without a frame count (a live agent): the others never wait for it
    camera: list = field(default_factory=list)  # its Join's [fx, fy, cx, cy, width, height] of the input frames
    done: L.Done | None = None
    processed: int = 0  # keyframes handed to the server
    last_heard: float = 0.0
    lost: bool = False
    ack: list = field(default_factory=list)  # message ids to acknowledge
    duplicates: int = 0  # messages received again (resent, or duplicated on the way)
    repeats: int = 0  # keyframes and submaps received again under new ids (from an agent resumed from a checkpoint)
    unique_bytes: dict = field(default_factory=dict)  # message kind -> bytes of the first copies

    def ended(self, frames: int = 0) -> bool:
        """Lost, or done with every keyframe handed over and every submap and frame pose received (`frames`:
        frame poses the server holds)."""
        d = self.done
        return self.lost or (d is not None and self.processed >= d.keyframes and len(self.submaps) >= d.submaps
                             and frames >= d.frames)

    def sent_all(self, frames: int = 0) -> bool:
        """Done, and every keyframe (with its images, or dropped), submap and frame pose it announces is here,
        handed over or waiting its turn: the agent has nothing left to send, so its silence is no loss."""
        d = self.done
        return d is not None and len(self.submaps) >= d.submaps and frames >= d.frames and all(
            k < self.processed or (k in self.meta and (k in self.images or k in self.dropped))
            for k in range(d.keyframes))

    def update_frontier(self) -> None:
        have = self.processed
        while have in self.meta:
            have += 1
        for r, k in self.claims:
            if k <= have:
                self.rounds_done = max(self.rounds_done, r)
        self.claims = [(r, k) for r, k in self.claims if r > self.rounds_done]


class ServerNode:
    """Mirrors + Server + link (module docstring). `team`: a slam.run.team.Team built with AgentMirror agents."""

    def __init__(self, team, tx, *, journal: Path | None = None, say=None, clock=time.monotonic):
        self.team, self.tx, self.cfg, self.clock = team, tx, team.cfg, clock
        self.peers = [Peer(ag.name) for ag in team.agents]
        self.t0 = clock()
        for p in self.peers:
            p.last_heard = self.t0
        self.digest = config_digest(self.cfg)
        self.say = say or (lambda *a: print(*a, file=sys.stderr, flush=True))
        self._stamp = 0  # optimisations whose corrections were sent
        self.feed = None  # what the team's state is published to (slam.run.ros2.team_feed), if anything
        self._ticking = (False, None, 0.0)  # `run`'s (progress, timeout, last status line) for `_tick`
        self.replayed = 0
        self._journal = None
        if journal is not None:
            journal.parent.mkdir(parents=True, exist_ok=True)
            if journal.is_file():
                self.replayed, whole = self._replay(journal)
                with open(journal, "r+b") as f:  # new records follow the last whole one, not a cut one
                    f.truncate(whole)
            self._journal = open(journal, "ab")

    # ---- messages -------------------------------------------------------------------------------------------

    def _replay(self, path: Path) -> tuple[int, int]:
        """Handle every whole record of the journal again; returns (records, bytes they take)."""
        data, off, n = path.read_bytes(), 0, 0
        while off + 4 <= len(data):
            (size,) = struct.unpack_from("<I", data, off)
            if off + 4 + size > len(data):
                break  # a record cut by a kill: it was not acknowledged, the agent resends it
            try:
                h, msg = L.LINK.decode(data[off + 4: off + 4 + size])
            except MessageError as e:
                self.say(f"[server] {path}: a damaged record at byte {off} ({e}); replayed up to it")
                break
            self.handle(h.sender - 1, msg, journal=False)
            off += 4 + size
            n += 1
        for p in self.peers:
            p.ack = []
        if n:
            self.say(f"[server] replayed {n} messages from {path}")
        return n, off

    def handle(self, a: int, msg: L.Message, *, journal: bool = True) -> None:
        """One agent message (a: agent index). Idempotent by message id."""
        if not 0 <= a < len(self.peers):
            return
        p = self.peers[a]
        p.last_heard = self.clock()
        if p.lost:
            p.lost = False
            self.say(f"[server] {p.name} is back")
        if isinstance(msg, L.Join):
            self._join(a, msg)
        if msg.mid in p.seen:
            p.ack.append(msg.mid)
            p.duplicates += 1
            return
        if isinstance(msg, L.Join) and msg.config != self.digest:
            return  # refused (Welcome ok=0): not kept, not acknowledged
        p.seen.add(msg.mid)
        p.ack.append(msg.mid)
        data = L.LINK.encode(msg, a + 1, 0)  # the size on the wire (only the header's sequence number differs)
        p.unique_bytes[msg.kind] = p.unique_bytes.get(msg.kind, 0) + len(data)
        if journal and self._journal is not None:
            self._journal.write(struct.pack("<I", len(data)) + data)
            self._journal.flush()
        # kept by keyframe id, submap id and frame index: an agent resumed from its checkpoint makes again what its
        # killed process may have sent, under new message ids (slam.run.team_link.member); the first copy stays
        if isinstance(msg, L.KeyframeMeta):
            p.repeats += msg.id in p.meta
            p.meta.setdefault(msg.id, msg)
        elif isinstance(msg, L.KeyframeImage):
            p.repeats += msg.id < p.processed or msg.id in p.images
            if msg.id >= p.processed:
                p.images.setdefault(msg.id, msg)
        elif isinstance(msg, L.SubmapData):
            p.repeats += msg.id in p.submaps
            p.submaps.setdefault(msg.id, msg)
            self.install_submaps(a)
        elif isinstance(msg, L.Frames):
            self._frames(a, msg)
        elif isinstance(msg, L.Done):
            p.done = msg
            self.team.agents[a].finish(msg.tracking_s, msg.mapping_s, msg.frames, msg.non_finite_dropped)
        p.update_frontier()

    def _join(self, a: int, msg: L.Join) -> None:
        p = self.peers[a]
        if msg.config != self.digest:
            self.tx.send(a + 1, L.Welcome(agent=a, ok=0, reason=f"its config differs from the server's (digest "
                                                                   f"{msg.config} vs {self.digest}): give both the "
                                                                   f"same --config"))
            return
        if not p.joined:
            ag = self.team.agents[a]
            ag.name, ag.camera = msg.name, _camera(msg.camera)
            p.name, p.joined, p.open_ended = msg.name, True, int(msg.rounds) == 0
            p.camera = list(msg.camera)
            self.say(f"[server] {msg.name} joined as agent {a}")
        self.tx.send(a + 1, L.Welcome(agent=a, ok=1))

    def _frames(self, a: int, msg: L.Frames) -> None:
        p, ag = self.peers[a], self.team.agents[a]
        ag.add_frames([FramePose(int(i), float(t), int(s), T) for i, t, s, T in
                       zip(msg.frame_index, msg.timestamp, msg.submap_id, msg.T_local_cam)])
        for i, reason in msg.skipped:
            ag.skip(i, reason)
        p.dropped.update(int(k) for k in msg.dropped)
        p.claims.append((int(msg.rounds_done), int(msg.keyframes)))

    def poll(self) -> int:
        """Handle what arrived, acknowledge it, mark silent agents lost. Returns the messages handled."""
        got = self.tx.poll()
        for h, msg in got:
            self.handle(h.sender - 1, msg)
        if any(p.ack for p in self.peers):  # on disk before acknowledged: an agent forgets what is acknowledged
            fsync_journal(self)
        for a, p in enumerate(self.peers):
            if p.ack:
                self.tx.send(a + 1, L.Ack(mids=np.array(sorted(set(p.ack)), np.int64)))
                p.ack = []
        now = self.clock()
        for a, p in enumerate(self.peers):
            # an agent that sent everything and ended is silent while the server works through its keyframes
            if not self._ended(a) and not p.lost and now - p.last_heard > self.cfg.link.agent_timeout_s \
                    and not p.sent_all(len(self.team.agents[a].poses)):
                p.lost = True
                self.say(f"[server] {p.name}: nothing heard for {now - p.last_heard:.0f} s "
                         f"(link.agent_timeout_s): reported lost; the others go on without it")
        return len(got)

    def _ended(self, a: int) -> bool:
        return self.peers[a].ended(len(self.team.agents[a].poses))

    # ---- the server, in the in-process order ---------------------------------------------------------------------

    def next_keyframe(self) -> tuple[int, L.KeyframeMeta] | None:
        """The keyframe the in-process team would hand the server next, if it may go now (module docstring)."""
        best = None
        for a, p in enumerate(self.peers):
            m = p.meta.get(p.processed)
            if m is None:
                continue
            ready = m.id in p.images or m.id in p.dropped
            if not ready and p.lost:  # its images will not come: the others do not wait for them
                continue
            if best is None or (m.round, a) < best[0]:
                best = ((m.round, a), a, m, ready)
        # The first keyframe in the in-process order goes first: one whose images are still on their way (resent
        # after a server restart, say) holds back every later one, though its agent has reported later rounds.
        if best is None or not best[3]:
            return None
        (r, a), _, m, _ = best
        for b, q in enumerate(self.peers):
            if b != a and not self._ended(b) and not q.open_ended and q.rounds_done < (r + 1 if b < a else r):
                return None
        return a, m

    def process(self) -> int:
        """Hand every keyframe that may go to the server; returns how many went."""
        n = 0
        while (nxt := self.next_keyframe()) is not None:
            self._process(*nxt)
            n += 1
            self.poll()  # acknowledge while the server works
            self._tick()  # and publish, report and keep the deadline: a backlog can last minutes
        return n

    def _process(self, a: int, m: L.KeyframeMeta) -> None:
        p, team = self.peers[a], self.team
        ag = team.agents[a]
        img = p.images.pop(m.id, None)
        small = map_rgbd = None
        if img is not None:
            try:
                small, map_rgbd = decode_images(img)
            except MessageError as e:
                self.say(f"[server] {p.name} keyframe {m.id}: {e}; kept without images")
                img = None
        if img is None:  # dropped by the agent's queue: a keyframe without images, never a loop candidate
            small = _blank(ag.camera, ag.cfg.submaps.keep_keyframe_width)
        n_sm = len(ag.gmap.submaps)
        kf = ag.add_keyframe(m.id, m.frame_index, m.timestamp, m.submap_id, m.T_local_cam[0],
                             m.descriptor if img is not None else None, small, map_rgbd,
                             (m.odom_T[0], m.odom_info[0]) if len(m.odom_T) else None,
                             m.submap_start[0] if len(m.submap_start) else None,
                             exposure=m.exposure if len(m.exposure) else None)
        p.processed += 1
        if len(ag.gmap.submaps) > n_sm:
            team._record_origin(a)
            self.install_submaps(a)  # a submap whose Gaussians came before its first keyframe
        team.rounds = m.round
        team.frames_done[a] = len(ag.poses)
        if img is not None:
            team.server.on_keyframe(a, kf, m.round)
        if team.server.optimisations > self._stamp:
            self._stamp = team.server.optimisations
            self.send_corrections()

    def send_corrections(self) -> None:
        srv = self.team.server
        for a, ag in enumerate(self.team.agents):
            sms = ag.gmap.submaps
            self.tx.send(a + 1, L.Correction(
                stamp=self._stamp, submap_ids=np.arange(len(sms), dtype=np.int64),
                T_world_local=np.stack([s.T_world_local for s in sms]) if sms else np.zeros((0, 4, 4)),
                T_global_world=srv.slots[a].T_global_world[None]))

    # ---- the whole run -----------------------------------------------------------------------------------------

    def step(self) -> int:
        """Read the link once and hand over every keyframe that may go; returns how much happened."""
        return self.poll() + self.process()

    def all_ended(self) -> bool:
        return all(self._ended(a) for a in range(len(self.peers)))

    def run(self, *, progress: bool = True, timeout: float | None = None) -> None:
        """Serve until every agent has finished (all its keyframes handled) or is lost."""
        self._ticking = (progress, timeout, time.monotonic())
        while not self.all_ended():
            busy = self.step()
            self._tick()
            if not busy:
                time.sleep(0.02)
        self.collect_submaps()

    def _tick(self) -> None:
        """Between keyframes, also inside a backlog: the feed's update, a status line every 10 s, the deadline."""
        if self.feed is not None:
            self.feed.step(self)
        progress, timeout, last = self._ticking
        now = time.monotonic()
        if progress and now - last > 10:
            self._ticking = (progress, timeout, now)
            self.say("[server] " + self.status())
        if timeout is not None and now - self.t0 > timeout:
            raise TimeoutError(f"the team server gave up after {timeout:.0f} s: {self.status()}")

    def install_submaps(self, a: int) -> None:
        """Agent `a`'s finished submaps received so far into its mirror, each once, as soon as the mirror has the
        submap: the server's checks that draw an agent's map while it serves (the cloud route's render check,
        slam.dense.loops.render_check) see the Gaussians of its finished submaps, as the team in one process sees
        them (there, also those of the submap being mapped). A submap's first copy is the one kept."""
        p, ag = self.peers[a], self.team.agents[a]
        for sid in sorted(set(p.submaps) - p.installed):
            if sid < len(ag.gmap.submaps):
                ag.set_submap(sid, p.submaps[sid].params())
                p.installed.add(sid)

    def collect_submaps(self) -> None:
        """Every finished submap's Gaussians into its mirror (those not installed while serving)."""
        for a in range(len(self.peers)):
            self.install_submaps(a)

    def status(self) -> str:
        parts = []
        for a, p in enumerate(self.peers):
            state = "lost" if p.lost else "done" if self._ended(a) else "joined" if p.joined else "waiting"
            parts.append(f"{p.name} {state} {p.processed} kf / {p.rounds_done} rounds")
        held = held_bytes(self.team, self.peers) / 2**20  # the map it keeps (slam.dense.team.held)
        return ("; ".join(parts) + "  |  " + self.team.status(0, 0, time.monotonic() - self.t0).split("  ", 1)[1]
                + f"  held {held:.0f} MB")

    def finished(self, status: str = "complete") -> None:
        """Tell the agents the results are written (several times: a lost copy must not keep one waiting)."""
        for _ in range(3):
            self.tx.send(None, L.Finished(status=status))
            time.sleep(0.05)
        self.close()

    def close(self) -> None:
        """Close the journal (what a server that stops, or is killed, leaves behind)."""
        if self._journal is not None:
            self._journal.close()
            self._journal = None

    def link_metrics(self) -> dict:
        """metrics.json "link": bytes per agent and message kind, per keyframe and per submap, against the agent's
        keyframes sent raw (8-bit RGB + 16-bit depth at its input frames' size)."""
        agents, total, raw_sizes = {}, 0, set()
        for a, p in enumerate(self.peers):
            st = self.tx.peer_stats[a + 1]
            recv, sent = dict(st.recv_bytes), dict(st.sent_bytes)
            n_kf, n_sm = p.processed, len(p.submaps)
            once = p.unique_bytes
            kf_bytes = once.get("KeyframeMeta", 0) + once.get("KeyframeImage", 0)
            both = int(sum(recv.values()) + sum(sent.values()))
            total += both
            raw_kf = raw_keyframe_bytes(p.camera) if p.camera else None
            raw_sizes.add(raw_kf)
            raw = n_kf * raw_kf if raw_kf else 0
            agents[p.name] = {
                "bytes_from_agent": recv, "messages_from_agent": dict(st.recv_count),
                "bytes_to_agent": sent, "messages_to_agent": dict(st.sent_count),
                "bytes_total": both, "keyframes": n_kf, "submaps": n_sm,
                "bytes_per_keyframe": kf_bytes / n_kf if n_kf else None,
                "image_bytes_per_keyframe": once.get("KeyframeImage", 0) / n_kf if n_kf else None,
                "bytes_per_submap": once.get("SubmapData", 0) / n_sm if n_sm else None,
                "bytes_from_agent_first_copies": dict(once), "duplicates_received": p.duplicates,
                "repeats_received": p.repeats,
                "input_size": list(p.camera[4:6]) if p.camera else None, "raw_keyframe_bytes": raw_kf,
                "raw_rgbd_bytes": raw, "fraction_of_raw": both / raw if raw else None,
                "raw_rgbd_640x480_bytes": n_kf * REFERENCE_KEYFRAME_BYTES,
                "dropped_images": len(p.dropped), "lost": p.lost,
                "agent_side": dict(p.done.link) if p.done is not None else None,
            }
        shared = raw_sizes - {None}
        return {"gaussians": self.cfg.link.gaussians,
                "raw_keyframe_bytes": shared.pop() if len(shared) == 1 else None,  # the agents' frames' size
                "bytes_total": total, "rejected_messages": self.tx.stats.rejected, "replayed_messages": self.replayed,
                "lost_agents": [p.name for p in self.peers if p.lost], "agents": agents}


def _blank(camera: PinholeCamera, width: int) -> RGBD:
    """A keyframe image with no valid depth, for a keyframe whose images were dropped."""
    z = RGBD(np.zeros((camera.height, camera.width, 3), np.uint8), np.zeros((camera.height, camera.width), np.float32),
             camera)
    return z.resized(width)


def fsync_journal(node: ServerNode) -> None:
    if node._journal is not None:
        node._journal.flush()
        os.fsync(node._journal.fileno())
