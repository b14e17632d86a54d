"""A team agent's checkpoints: an agent process of a team (`swarmsplat agent DATA --server ... --out DIR`, each agent
of `swarmsplat run --processes`) keeps progress/checkpoint.pkl and progress/poses.tum in its folder as a lone agent
does (slam.run.checkpoint): the agent, the messages the server has not acknowledged, what has been sent, the next
round to read and the journal's state. `--resume` continues from it and joins the server again.

Taken back without duplicates. The resumed agent tracks again the rounds after its checkpoint, so it makes again
keyframes, submaps and frame poses that the killed process may have sent already. The server keeps what it has by
keyframe id, submap id and frame index and drops the repeats (slam.run.team_link.server_node,
slam.dense.team.mirror). Each restart numbers its new messages in a range of its own (progress/link_epoch counts
the restarts; restart e numbers from e * 2**32 on), so a message of the killed process that the server has, under
an id the checkpoint does not know, never hides a new message with the same id; messages queued at the checkpoint
keep their ids, their content is what was sent.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from swarmsplat.kernels.errors import InputError
from swarmsplat.kernels.fileio import atomic_write_text

from swarmsplat.slam.run.checkpoint import CHECKPOINT, PoseJournal, find_resume, run_identity, save_checkpoint
from swarmsplat.slam.run.sequence import JOURNAL
EPOCH = Path("progress") / "link_epoch"
MID_RANGE = 1 << 32  # message ids of one process life


def member_identity(seq, cfg, n_frames: int, index: int, stride: int) -> dict:
    """What a team agent's checkpoint must share with the process that resumes it: `run_identity` (the sequence,
    the frames, the config) and the agent's index in the team and frame stride."""
    return {**run_identity(seq, cfg, n_frames), "team_index": int(index), "frame_stride": int(stride)}


def member_complete(out: Path) -> bool:
    """Whether the team agent in `out` ended with everything acknowledged by its server (link.json)."""
    try:
        return bool(json.loads((Path(out) / "link.json").read_text()).get("acknowledged"))
    except (OSError, ValueError, AttributeError):
        return False


def forget_member(out: Path) -> None:
    """Remove what says where an earlier team agent in `out` stood (checkpoint, restarts, link.json)."""
    for name in (CHECKPOINT, EPOCH, Path("link.json")):
        (Path(out) / name).unlink(missing_ok=True)


def agent_folder(out: Path, name: str) -> Path:
    """Where `run --processes` keeps agent `name`'s own folder (its checkpoint, journal, link.json, log)."""
    return Path(out) / "link" / name


def team_resume(out: Path, identity: dict, *, resume: bool) -> None:
    """`run --processes`: write link/identity.json (the team's dataset, frames, stride and config) for a new run;
    with `resume`, check that `out` holds an unfinished run of agent processes with this identity (InputError, one
    line naming the file and what differs)."""
    from swarmsplat.slam.run.checkpoint.state import differences

    path = Path(out) / "link" / "identity.json"
    if not resume:
        path.parent.mkdir(exist_ok=True)
        atomic_write_text(path, json.dumps(identity, indent=1))
        return
    try:
        status = json.loads((Path(out) / "metrics.json").read_text()).get("status")
    except (OSError, ValueError, AttributeError):
        status = None
    if status == "complete":
        raise InputError(f"--resume: {out} holds a complete run (metrics.json status 'complete'); nothing to resume")
    try:
        saved = json.loads(path.read_text())
    except (OSError, ValueError):
        raise InputError(f"--resume: {out} holds no run of agent processes to resume (no readable {path.name} in "
                         f"{path.parent}; a run in one process resumes without --processes)") from None
    differs = differences(saved, identity) if isinstance(saved, dict) else ["not a run's identity"]
    if differs:
        raise InputError(f"--resume: {out} is a run of another dataset or config ({path}): " + "; ".join(differs))


class MemberCheckpoints:
    """One team agent's checkpoints in `out`, taken as `swarmsplat run` takes them (config checkpoint.every_submaps:
    each time that many more submaps are finished, and after the last round) and removed once the server has
    acknowledged everything."""

    def __init__(self, out: Path, identity: dict, cfg):
        self.out, self.identity, self.every = Path(out), identity, cfg.checkpoint.every_submaps
        self.t0 = time.perf_counter()
        self._cfg = cfg

    def open(self, resume: bool):
        """Take this folder for this process (progress/lock) and, with `resume`, read its checkpoint: the
        slam.run.checkpoint.Resumed to go on from, or None (killed before its first checkpoint: from the first
        round). InputError (one line) when the folder holds no run of this agent, a complete one, or one of another
        dataset or config. Call before connecting: a bad folder stops the agent at once."""
        self._lock()
        self.resume, resumed = resume, None
        if resume:
            if member_complete(self.out):
                raise InputError(f"--resume: {self.out} holds a team agent whose server acknowledged everything "
                                 f"(link.json); nothing to resume")
            resumed = find_resume(self.out, self.identity)
            if resumed is not None and not hasattr(resumed.agent, "outbox"):
                raise InputError(f"--resume: {self.out / CHECKPOINT} is the checkpoint of a lone agent, not of a "
                                 f"team agent; resume it without --server")
        atomic_write_text(self.out / "config.yaml", self._cfg.to_yaml())
        return resumed

    def start(self, resumed, make_node, tx, *, say=None):
        """(the node, the first round to read): the checkpoint's node (`open`'s `resumed`) on transport `tx`, or a
        new one from `make_node()`."""
        if resumed is not None:
            node = resumed.agent
            node.reattach(tx, PoseJournal(self.out / JOURNAL, resume=resumed.journal), self._next_epoch())
            self.t0 -= resumed.wall_s
            start = resumed.next_frame
        else:
            node = make_node()
            node.journal = PoseJournal(self.out / JOURNAL)
            if self.resume:  # killed before its first checkpoint: from the first round, under new message ids
                node.outbox.reattach(tx, self._next_epoch())
            else:  # a new run in this folder: an earlier run's checkpoint and end are not this one's
                forget_member(self.out)
            start = 0
        if self.resume and say is not None:
            say(f"[{node.name}] resuming at round {start}" if resumed else
                f"[{node.name}] no checkpoint in {self.out} yet: starting from the first round")
        return node, start

    def _lock(self, wait_s: float = 30.0) -> None:
        """Hold progress/lock while this process runs: one agent process per folder. A process of a killed
        `run --processes` may still be ending (it stops at its next link service): wait for it, at most wait_s."""
        import fcntl
        import os

        path = self.out / "progress" / "lock"
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        t_end = time.monotonic() + wait_s
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except OSError:
                if time.monotonic() > t_end:
                    os.close(fd)
                    raise InputError(f"--out {self.out}: another agent process is running in it ({path} is "
                                     f"locked)") from None
                time.sleep(0.1)
        self._lock_fd = fd

    def close(self) -> None:
        """Let go of the folder (progress/lock; a process that ends lets go of it anyway)."""
        import os

        if getattr(self, "_lock_fd", None) is not None:
            os.close(self._lock_fd)  # closing the file releases its lock
            self._lock_fd = None

    def _next_epoch(self) -> int:
        """This process life's first message id: (restarts so far + 1) * MID_RANGE."""
        path = self.out / EPOCH
        try:
            epoch = int(path.read_text().strip() or 0) + 1
        except (OSError, ValueError):
            epoch = 1
        atomic_write_text(path, f"{epoch}\n")
        return epoch * MID_RANGE

    def after_round(self, node, i: int, submaps_before: int) -> bool:
        """After round i: a checkpoint when it finished the every_submaps-th submap (the next round is i + 1).
        Returns whether it wrote one."""
        finished = len(node.agent.gmap.submaps) - 1
        if self.every and len(node.agent.gmap.submaps) > submaps_before and finished and finished % self.every == 0:
            self.save(node, i + 1)
            return True
        return False

    def save(self, node, next_round: int) -> None:
        if self.every:
            save_checkpoint(self.out, self.identity, node, next_frame=next_round, journal=node.journal.state(),
                            wall_s=time.perf_counter() - self.t0)

    def done(self) -> None:
        """The server has everything: no checkpoint is needed any more (the journal stays)."""
        (self.out / CHECKPOINT).unlink(missing_ok=True)
