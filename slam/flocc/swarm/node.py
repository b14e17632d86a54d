"""One robot of the decentralised FLOCC-SLAM team (§III): keyframes in, loop closures and a global estimate out.

Each tick a node
    1. handles what arrived (idempotently: duplicates, reordering and late messages change nothing twice);
    2. says hello to whoever is in range (what it has: keyframes, descriptors, loops, graphs, estimate);
    3. sends each neighbour only what that neighbour's last hello says it lacks (descriptors, loops, estimate);
    4. for every neighbour with a higher id, searches candidates by descriptor cosine similarity, asks for the
       encodings of matched keyframes it does not hold, registers, gates (`slam.flocc.frontend.LoopFrontend`) and
       shares the loops with that neighbour (the lower-id robot of a pair registers it, so it is done once);
    5. elects the optimiser (lowest id in range): a follower submits its graph when the optimiser lacks its
       latest version; the optimiser solves once every member's latest graph is in and broadcasts the estimate.
       With `solve.solver` "distributed" there is no optimiser: the robot steps its own part of the distributed
       solver instead (distributed.py) and sends its neighbours their separators.
A node keeps its odometry (its own frame) and the newest global estimate that includes it (`Estimate` stamps:
more keyframes, then more robots, then more loops, then later), so a late or repeated estimate never replaces a
newer one, and a robot that returns catches up from any neighbour's newer estimate.

A pair's loops are the accepted registrations of the *current* candidate set (best match per keyframe among
all descriptors known), each registration computed once and cached: the outcome depends on what is known, not
on the order it arrived in, which is why a Zenoh run ends with the same estimates as the in-process one.
Remote encodings are put into the front-end's per-keyframe encoding cache (`LoopFrontend.put_encoding`), so a
robot never needs another robot's images.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field

import numpy as np

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import InputError, SwarmsplatError

from . import messages as M
from .election import elect, is_optimiser
from .optimiser import SolveConfig, robot_char, solve_group
from .transport import Transport


@dataclass
class NodeConfig:
    threshold: float = 0.1  # cosine similarity of a candidate (FLOCC §IV: 0.1)
    r_thr: float | None = None  # eq. 1 gate (None: slam.flocc.frontend.default_r_thr of the pair backend)
    k: float | None = None  # eq. 2 steepness
    neighbour_timeout: int = 3  # ticks without a hello before a robot counts as out of range
    resend: int = 4  # ticks before re-sending something a neighbour still lacks
    end_timeout: float = 60.0  # seconds the end protocol may run after the schedule's last tick (ending.py)
    solve: SolveConfig = field(default_factory=SolveConfig)


@dataclass
class Loop:
    T_query_match: np.ndarray  # [4, 4], unit translation
    confidence: float
    odom_scale: float


def _lb_rows(lb) -> list[tuple[tuple[int, int, int, int], Loop]]:
    return [((int(lb.query_robot[n]), int(lb.query_index[n]), int(lb.match_robot[n]), int(lb.match_index[n])),
             Loop(lb.T_query_match[n], float(lb.confidence[n]), float(lb.odom_scale[n])))
            for n in range(len(lb.query_robot))]


def _loop_arrays(items) -> dict:
    items = sorted(items, key=lambda kv: kv[0])
    k = np.array([key for key, _ in items], dtype=np.int64).reshape(-1, 4)
    return {"query_robot": k[:, 0], "query_index": k[:, 1], "match_robot": k[:, 2], "match_index": k[:, 3],
            "T_query_match": np.array([lp.T_query_match for _, lp in items]).reshape(-1, 4, 4),
            "confidence": np.array([lp.confidence for _, lp in items], float),
            "odom_scale": np.array([lp.odom_scale for _, lp in items], float)}


def stamp_of(est: M.Estimate | None) -> list[int]:
    return list(est.stamp) if est is not None else []


class RobotNode:
    """A robot (see the module docstring). `recognizer` describes images (registration.place_recognition);
    `registrar` encodes and registers pairs (registration.pair); both must be the same on every robot."""

    def __init__(self, robot: int, camera: PinholeCamera, transport: Transport, recognizer, registrar,
                 config: NodeConfig | None = None):
        from swarmsplat.graph.confidence import K_DEFAULT
        from swarmsplat.slam.flocc.frontend import LoopFrontend

        self.id, self.char = int(robot), robot_char(int(robot))
        self.camera, self.tx, self.cfg = camera, transport, config or NodeConfig()
        self.recognizer, self.registrar = recognizer, registrar
        self.images: list[np.ndarray] = []
        self.odometry: list[np.ndarray] = []  # T_odom_kf
        self.timestamps: list[float] = []
        self.own_desc: list[np.ndarray] = []
        self.desc: dict[int, dict[int, np.ndarray]] = {}  # robot -> keyframe -> descriptor
        self.cameras: dict[int, PinholeCamera] = {self.id: camera}
        self.front = LoopFrontend(registrar, self._image_of, self._camera_of, self._count_of,
                                  k=K_DEFAULT if self.cfg.k is None else self.cfg.k,
                                  r_thr=self.cfg.r_thr)
        self.registered: dict[tuple, object] = {}  # (peer, i, j) -> LoopMeasurement, computed once
        self.loops: dict[int, dict[tuple, Loop]] = {}  # peer -> loop key (qa, qi, mb, mj) -> Loop
        self.loops_version: dict[int, list[int]] = {}  # peer (lower id) -> version of the set received
        self.hello: dict[int, M.Hello] = {}
        self.finish: dict[int, M.Finish] = {}  # robot -> its latest Finish (the end protocol, ending.py)
        self.last_seen: dict[int, int] = {}
        self.subs: dict[int, M.GraphSubmission] = {}  # as optimiser: robot -> latest submission
        self.estimate: M.Estimate | None = None
        self.solved_basis: dict | None = None
        self.last_solution = None  # GroupSolution of this robot's last solve (for outputs)
        self.n_solves = 0
        self._sent: dict[tuple, tuple] = {}  # (what, peer) -> (content, tick): resend bookkeeping
        self._dirty: set[int] = set()  # peers whose candidates must be searched again
        self._pending: set[int] = set()  # peers whose encodings we asked for and still lack (ask again)
        self._asked: dict[tuple[int, int], int] = {}  # (peer, keyframe) -> tick its encoding was last requested
        self.tick = 0
        self.dist = None  # this robot's part of the distributed solve (swarm.solver distributed), else the gather
        if self.cfg.solve.solver == "distributed":
            from .distributed import SwarmPart

            self.dist = SwarmPart(self, wait=self.cfg.neighbour_timeout)

    # ------------------------------------------------------------------------------------------ inputs
    def add_keyframe(self, image: np.ndarray, T_odom_kf: np.ndarray, timestamp: float = 0.0) -> int:
        """Take keyframe `image` (RGB uint8 [H, W, 3]) with its metric odometry pose T_odom_kf [4, 4]."""
        self.images.append(image)
        self.odometry.append(np.asarray(T_odom_kf, dtype=np.float64))
        self.timestamps.append(float(timestamp))
        self.own_desc.append(np.asarray(self.recognizer.describe(image), np.float32))
        self._dirty.update(r for r in self.desc if r > self.id)
        return len(self.images) - 1

    def _image_of(self, agent: str, i: int) -> np.ndarray:
        if agent != self.char:
            raise KeyError(f"robot {self.char} holds no image of robot {agent}")  # remote encodings are cached
        return self.images[i]

    def _camera_of(self, agent: str) -> PinholeCamera:
        return self.cameras[ord(agent) - ord("a")]

    def _count_of(self, agent: str) -> int:
        return len(self.images) if agent == self.char else len(self.desc.get(ord(agent) - ord("a"), {}))

    # ------------------------------------------------------------------------------------------ state
    def neighbours(self) -> list[int]:
        return sorted(r for r, t in self.last_seen.items() if self.tick - t <= self.cfg.neighbour_timeout)

    def own_loops(self) -> dict[tuple, Loop]:
        return {k: lp for peer in sorted(self.loops) for k, lp in self.loops[peer].items()}

    def graph_version(self) -> list[int]:
        mine = sorted((k, round(lp.confidence, 6)) for k, lp in self.own_loops().items() if k[0] == self.id)
        return [len(self.images), zlib.crc32(repr(mine).encode())]

    def _have_desc(self) -> dict:
        out = {}
        for r, d in self.desc.items():
            n = 0
            while n in d:
                n += 1
            out[str(r)] = n
        return out

    def _due(self, what: str, peer: int, content) -> bool:
        """True (and noted) unless the same content went to `peer` less than `resend` ticks ago."""
        last = self._sent.get((what, peer))
        if last is not None and last[0] == content and self.tick - last[1] < self.cfg.resend:
            return False
        self._sent[(what, peer)] = (content, self.tick)
        return True

    # ------------------------------------------------------------------------------------------ the tick
    def step(self, tick: int) -> None:
        """One tick: receive, greet, sync, close loops, optimise (module docstring)."""
        self.tick = int(tick)
        for h, msg in self.tx.poll():
            self._handle(h.sender, msg)
        self.tx.send(None, M.Hello(
            tick=self.tick, n_keyframes=len(self.images), have_desc=self._have_desc(),
            loops_with={str(p): self._loops_digest(p) for p in self.loops}, graph_version=self.graph_version(),
            graphs_held={str(r): list(s.version) for r, s in self.subs.items()},
            estimate_stamp=stamp_of(self.estimate)))
        nb = self.neighbours()
        for peer in nb:
            self._sync(peer)
        for peer in sorted(self._dirty | (self._pending & set(nb))):
            self._close_loops(peer)
        self._dirty.clear()
        if self.dist is not None:
            self.dist.tick(self.tick, nb)
            return
        leader = elect(self.id, nb)
        if leader != self.id and leader in self.hello:
            self._submit(leader)
        if is_optimiser(self.id, nb):
            self._maybe_solve(nb)

    def _handle(self, sender: int, msg: M.Message) -> None:
        if isinstance(msg, M.Hello):
            if msg.tick >= self.hello.get(sender, msg).tick:  # a late hello must not roll back what we know
                self.hello[sender] = msg
            self.last_seen[sender] = max(self.last_seen.get(sender, -1), self.tick)
        elif isinstance(msg, M.Descriptors):
            if msg.owner != sender or msg.descriptors.shape[1] != int(self.recognizer.dim):
                return  # relayed (only the owner sends its descriptors) or another place-recognition model
            d = self.desc.setdefault(msg.owner, {})
            new = [int(i) for i in msg.indices if int(i) not in d]
            for i, v in zip(msg.indices.tolist(), msg.descriptors):
                d.setdefault(int(i), v.copy())
            if new and msg.owner > self.id:
                self._dirty.add(msg.owner)
        elif isinstance(msg, M.EncodingRequest):
            if msg.owner == self.id:
                idx = [int(i) for i in msg.indices if 0 <= int(i) < len(self.images)]
                c = self.camera
                items = {i: self.front.encoding((self.char, i)).to_bytes() for i in idx}
                self.tx.send(sender, M.EncodingReply.pack(self.id, [c.fx, c.fy, c.cx, c.cy, c.width, c.height], items))
        elif isinstance(msg, M.EncodingReply):
            self._on_encodings(sender, msg)
        elif isinstance(msg, M.LoopBatch):
            if sender < self.id and list(msg.version) > self.loops_version.get(sender, []):
                rows = [(k, lp) for k, lp in _lb_rows(msg) if k[0] == sender and k[2] == self.id]
                self.loops[sender] = dict(rows)
                self.loops_version[sender] = list(msg.version)
        elif isinstance(msg, M.GraphSubmission):
            held = self.subs.get(msg.robot)
            if msg.robot == sender and (held is None or list(msg.version) != list(held.version)):
                if held is None or len(msg.odometry) >= len(held.odometry):  # never go back to fewer keyframes
                    self.subs[msg.robot] = msg
        elif isinstance(msg, M.Estimate):
            self._offer_estimate(msg)
        elif isinstance(msg, M.DistributedEstimate):
            if self.dist is not None:
                self.dist.on_message(sender, msg)
        elif isinstance(msg, M.Finish):
            if msg.tick >= self.finish.get(sender, msg).tick:
                self.finish[sender] = msg

    def _on_encodings(self, sender: int, msg: M.EncodingReply) -> None:
        from swarmsplat.registration.pair.base import Encoding

        if msg.owner != sender:  # only a keyframe's own robot encodes it
            return
        fx, fy, cx, cy, w, h = msg.camera
        self.cameras[msg.owner] = PinholeCamera(fx, fy, cx, cy, int(w), int(h))
        c = robot_char(msg.owner)
        for i, data in msg.items().items():
            if not self.front.has_encoding((c, i)):
                try:
                    self.front.put_encoding((c, i), Encoding.from_bytes(data))
                except InputError:
                    continue
        self._dirty.add(msg.owner)

    # ------------------------------------------------------------------------------------------ sync
    def _sync(self, peer: int) -> None:
        """Send `peer` what its latest hello says it lacks."""
        h = self.hello.get(peer)
        if h is None:
            return
        have = int(h.have_desc.get(str(self.id), 0))
        n = len(self.own_desc)
        upto, when = self._sent.get(("desc", peer), (0, -10**9))
        # what was sent recently is in flight: send only newer keyframes; after `resend` ticks, everything missing
        start = have if (have >= upto or self.tick - when >= self.cfg.resend) else upto
        if start < n:
            self._sent[("desc", peer)] = (n, self.tick)
            self.tx.send(peer, M.Descriptors(owner=self.id, indices=np.arange(start, n, dtype=np.int64),
                                             descriptors=np.stack(self.own_desc[start:n])))
        mine = self.loops.get(peer, {})
        digest = self._loops_digest(peer)
        if peer > self.id and int(h.loops_with.get(str(self.id), 0)) != digest and self._due("loops", peer, digest):
            self.tx.send(peer, M.LoopBatch(version=self._loop_version(peer), **_loop_arrays(mine.items())))
        if self.estimate is not None and list(h.estimate_stamp) < stamp_of(self.estimate) and \
                peer in self.estimate.robots.tolist() and self._due("estimate", peer, tuple(self.estimate.stamp)):
            self.tx.send(peer, self.estimate)

    def _loops_digest(self, peer: int) -> int:
        """CRC of the loop keys known with `peer` (0 for none), what hellos advertise."""
        keys = sorted(self.loops.get(peer, {}))
        return zlib.crc32(repr(keys).encode()) if keys else 0

    def _loop_version(self, peer: int) -> list[int]:
        return [len(self.images), len(self.desc.get(peer, {})), len(self.registered)]

    # ------------------------------------------------------------------------------------------ loops
    def _close_loops(self, peer: int) -> None:
        """Candidates with `peer` (a higher id) from all descriptors known; register those whose encoding is
        here; request the others; keep the accepted ones of the current candidate set."""
        d = self.desc.get(peer, {})
        if peer < self.id or not d or len(self.images) < 2:
            return
        js = sorted(d)
        sim = np.stack(self.own_desc) @ np.stack([d[j] for j in js]).T  # [n_own, n_peer] cosine
        cands = {}
        for i in range(sim.shape[0]):
            j = int(np.argmax(sim[i]))
            if sim[i, j] >= self.cfg.threshold:
                cands[(i, js[j])] = float(sim[i, j])
        for jj in range(sim.shape[1]):
            i = int(np.argmax(sim[:, jj]))
            if sim[i, jj] >= self.cfg.threshold:
                cands[(i, js[jj])] = float(sim[i, jj])
        c = robot_char(peer)
        need = sorted({j for (_, j) in cands if not self.front.has_encoding((c, j))})
        (self._pending.add if need else self._pending.discard)(peer)
        # ask for each encoding once; again only if it has not come `resend` ticks later (lost on the way)
        ask = [j for j in need if self.tick - self._asked.get((peer, j), -10**9) >= self.cfg.resend]
        if ask:
            self._asked.update({(peer, j): self.tick for j in ask})
            self.tx.send(peer, M.EncodingRequest(owner=peer, indices=np.array(ask, np.int64)))
        for (i, j), s in sorted(cands.items()):
            if (peer, i, j) not in self.registered and self.front.has_encoding((c, j)):
                try:
                    self.registered[(peer, i, j)] = self.front.evaluate((self.char, i), (c, j), s)
                except SwarmsplatError:  # e.g. an encoding from another backend: this pair is not a loop
                    self.registered[(peer, i, j)] = None
        loops = {}
        for (i, j) in sorted(cands):
            m = self.registered.get((peer, i, j))
            if m is None or not m.accepted:
                continue
            pair = m.odom_pair
            t_odo = np.linalg.inv(self.odometry[pair[0]]) @ self.odometry[pair[1]]
            t_net = float(np.linalg.norm(m.odom.t))
            scale = float(np.linalg.norm(t_odo[:3, 3])) / t_net if t_net > 0 else 1.0  # eq. 6
            loops[(self.id, i, peer, j)] = Loop(m.T_query_match, float(m.p), max(scale, 1e-6))
        self.loops[peer] = loops

    # ------------------------------------------------------------------------------------------ optimiser
    def submission(self) -> M.GraphSubmission:
        return M.GraphSubmission(robot=self.id, version=self.graph_version(),
                                 odometry=np.array(self.odometry).reshape(-1, 4, 4),
                                 **_loop_arrays(self.own_loops().items()))

    def _submit(self, leader: int) -> None:
        v = self.graph_version()
        if list(self.hello[leader].graphs_held.get(str(self.id), [])) != v and self._due("graph", leader, tuple(v)):
            self.tx.send(leader, self.submission())

    def _maybe_solve(self, nb: list[int]) -> None:
        self.subs[self.id] = self.submission()
        group = [self.id] + [r for r in nb if r in self.subs and r in self.hello]
        # a member whose advertised graph is newer than its submission here: wait for the newer one
        group = [r for r in group if r == self.id or list(self.hello[r].graph_version) == list(self.subs[r].version)]
        basis = {str(r): list(self.subs[r].version) for r in group}
        if len(group) < 2 or basis == self.solved_basis:
            return
        try:
            sol = solve_group({r: self.subs[r] for r in group}, self.cfg.solve)
        except SwarmsplatError:  # a graph the solver refuses: keep the current estimate, try with the next change
            self.solved_basis = basis
            return
        self.solved_basis, self.last_solution = basis, sol
        self.n_solves += 1
        est = M.Estimate(leader=self.id, anchor=min(group),
                         stamp=[int(sum(sol.counts)), len(group), sol.n_loops, self.tick],
                         basis=basis, formulation=self.cfg.solve.formulation, solver=self.cfg.solve.solver,
                         robots=np.array(sol.robots, np.int64), counts=np.array(sol.counts, np.int64),
                         poses=sol.poses, scales=sol.scales)
        self._offer_estimate(est)
        self.tx.send(None, est)

    def _offer_estimate(self, est: M.Estimate) -> bool:
        """Keep `est` if it includes this robot and is newer than the current one (stamps compare as lists)."""
        if self.id not in est.robots.tolist() or list(est.stamp) <= stamp_of(self.estimate):
            return False
        self.estimate = est
        return True

    # ------------------------------------------------------------------------------------------ outputs
    def trajectory(self) -> np.ndarray:
        """T_global_kf [n_kf, 4, 4]: the estimate where it covers this robot, odometry after its last estimated
        keyframe; the odometry itself (own frame) without an estimate."""
        if self.dist is not None and len(self.odometry):
            return self.dist.trajectory()
        odo = np.array(self.odometry).reshape(-1, 4, 4)
        if self.estimate is None:
            return odo.copy()
        est = self.estimate.per_robot()[self.id]
        out = odo.copy()
        c = min(len(est), len(odo))
        out[:c] = est[:c]
        if 0 < c < len(odo):
            out[c:] = est[c - 1] @ np.linalg.inv(odo[c - 1]) @ odo[c:]
        return out
