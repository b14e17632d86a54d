"""Checkpoints of a run (one agent, an in-process team, or one agent process of a team: slam.run.team_link.member),
and what `--resume` continues from.

progress/checkpoint.pkl holds two pickles one after the other: a small header (format, the run's identity: the
dataset and the config; the next frame (one agent) or round (a team) to read; the journals' state; the seconds
worked so far), then the Agent itself — submaps' Gaussians, keyframes with their images and descriptors, the loop
closer's edges and log, the tracker's last frame, pose and velocity, the mapper's random generator — or the Team
(every agent so, and the server: its pose graph, loop records, joins and cached encodings), so the resumed run
goes on exactly where the checkpoint was taken. It is written atomically (a kill while writing leaves the previous one), and removed when
the run completes. A pickle runs code when loaded: resume only folders your own runs wrote.
"""

from __future__ import annotations

import os
import pickle
from dataclasses import dataclass
from pathlib import Path

from swarmsplat.kernels.errors import InputError
from swarmsplat.kernels.fileio import atomic_path, remove_leftovers

FORMAT = 1
CHECKPOINT = Path("progress") / "checkpoint.pkl"


@dataclass
class Resumed:
    """What `load_checkpoint` gives back: the agent (or the team) and where its run stood."""

    agent: object  # slam.dense.agent.Agent, slam.run.team.Team for a team run, a team agent process's AgentNode
    next_frame: int  # the first input frame (team: round) not yet read
    journal: tuple  # PoseJournal.state() at the checkpoint; a team: one per agent
    wall_s: float  # seconds of run time before the checkpoint


def run_identity(seq, cfg, n_frames: int) -> dict:
    """What a checkpoint must share with the run that resumes it: the sequence (folder, name, frame count and
    time span, camera), the frames to process and the config (all but its `checkpoint` section)."""
    ts = seq.timestamps
    config = cfg.model_dump(mode="json")
    config.pop("checkpoint", None)  # how often to checkpoint does not change the result
    return {"dataset": str(Path(seq.root).resolve()), "sequence": seq.name, "sequence_frames": len(seq),
            "first_timestamp": round(float(ts[0]), 6) if len(ts) else None,
            "last_timestamp": round(float(ts[-1]), 6) if len(ts) else None,
            "camera": {k: float(v) for k, v in seq.camera.to_dict().items()}, "frames": int(n_frames),
            "config": config}


def team_identity(ds, cfg, caps, stride: int) -> dict:
    """`run_identity` of a team run: the dataset (folder, and per agent its name, frame count, time span and
    camera), each agent's frame cap, the frame stride and the config (all but its `checkpoint` section)."""
    config = cfg.model_dump(mode="json")
    config.pop("checkpoint", None)
    agents = []
    for seq in ds.agents:
        ts = seq.timestamps
        agents.append({"name": seq.name, "frames": len(seq),
                       "first_timestamp": round(float(ts[0]), 6) if len(ts) else None,
                       "last_timestamp": round(float(ts[-1]), 6) if len(ts) else None,
                       "camera": {k: float(v) for k, v in seq.camera.to_dict().items()}})
    return {"dataset": str(Path(ds.root).resolve()), "agents": {a["name"]: a for a in agents},
            "frame_caps": [int(c) for c in caps], "frame_stride": int(stride), "config": config}


def save_checkpoint(out: Path, identity: dict, agent, *, next_frame: int, journal, wall_s: float) -> Path:
    """Write out/progress/checkpoint.pkl atomically (fsync'd, then renamed over the previous one). `agent`: the
    Agent, or a team (anything with `.agents`); `journal`: its PoseJournal.state(), a team's one per agent."""
    path = Path(out) / CHECKPOINT
    # a team's agents; a team agent process's node (slam.run.team_link.member) holds its Agent as .agent
    agents = agent.agents if hasattr(agent, "agents") else [getattr(agent, "agent", agent)]
    header = {"format": FORMAT, "identity": identity, "next_frame": int(next_frame),
              "journal": [list(j) for j in journal] if hasattr(agent, "agents") else list(journal),
              "wall_s": float(wall_s), "keyframes": sum(len(a.keyframes) for a in agents),
              "submaps": sum(len(a.gmap.submaps) for a in agents)}
    path.parent.mkdir(parents=True, exist_ok=True)
    # The temporary file of a write that a kill cut short (SIGKILL leaves no time to remove it) is never a
    # checkpoint, and beside a checkpoint of hundreds of MB it can take the space the next one needs: found by a
    # soak, where such a leftover filled the agent's disk at its next checkpoint. One process owns `out` (its lock).
    remove_leftovers(path.parent, path.name, path.suffix)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            pickle.dump(header, f, protocol=pickle.HIGHEST_PROTOCOL)
            pickle.dump(agent, f, protocol=pickle.HIGHEST_PROTOCOL)
            f.flush()
            os.fsync(f.fileno())  # on disk before it replaces the previous checkpoint
    return path


def has_checkpoint(out: Path) -> bool:
    return (Path(out) / CHECKPOINT).is_file()


def load_checkpoint(out: Path, identity: dict) -> Resumed:
    """The checkpoint in `out`; InputError (one line, naming what differs) when it is not one of this dataset
    and config, or cannot be read."""
    path = Path(out) / CHECKPOINT
    try:
        with open(path, "rb") as f:
            header = pickle.load(f)
            if not isinstance(header, dict) or header.get("format") != FORMAT:
                raise InputError(f"--resume: {path} is not a checkpoint this version reads")
            differs = differences(header["identity"], identity)
            if differs:
                raise InputError(f"--resume: {out} is a checkpoint of another run: " + "; ".join(differs))
            agent = pickle.load(f)
    except InputError:
        raise
    except Exception as e:  # noqa: BLE001 - a truncated or foreign file: say so in one line
        raise InputError(f"--resume: cannot read the checkpoint {path}: {type(e).__name__}: {e}") from None
    journal = header["journal"]
    journal = [tuple(j) for j in journal] if journal and isinstance(journal[0], list) else tuple(journal)
    return Resumed(agent, header["next_frame"], journal, header["wall_s"])


def find_resume(out: Path, identity: dict) -> Resumed | None:
    """Where `--resume` continues in `out`: its checkpoint (load_checkpoint), or None — start from the first
    frame — when the run there was killed before its first checkpoint (its config.yaml must match). InputError
    when `out` holds no run, a complete one, or one of another config."""
    import json

    import yaml

    out = Path(out)
    if has_checkpoint(out):
        return load_checkpoint(out, identity)
    try:
        status = json.loads((out / "metrics.json").read_text()).get("status")
    except (OSError, ValueError, AttributeError):
        status = None
    if status == "complete":
        raise InputError(f"--resume: {out} holds a complete run (metrics.json status 'complete'); nothing to resume")
    try:
        config = yaml.safe_load((out / "config.yaml").read_text())
    except (OSError, yaml.YAMLError):
        raise InputError(f"--resume: {out} holds no run to resume (no {CHECKPOINT} and no readable config.yaml)") \
            from None
    if isinstance(config, dict):
        config.pop("checkpoint", None)
    differs = differences({"config": config}, {"config": identity["config"]})
    if differs:
        raise InputError(f"--resume: {out} is a run of another config: " + "; ".join(differs))
    return None


def differences(saved: dict, now: dict, *, limit: int = 4) -> list[str]:
    """'<key>: <checkpoint's> in the checkpoint, <this run's> now' for each leaf that differs (config keys
    dotted), the first `limit` of them and a count of the rest."""
    a, b = _flatten(saved), _flatten(now)
    keys = [k for k in list(a) + [k for k in b if k not in a] if a.get(k, _MISSING) != b.get(k, _MISSING)]
    out = [f"{k}: {_show(a.get(k, _MISSING))} in the checkpoint, {_show(b.get(k, _MISSING))} now" for k in keys[:limit]]
    if len(keys) > limit:
        out.append(f"and {len(keys) - limit} more")
    return out


_MISSING = object()


def _show(v) -> str:
    return "absent" if v is _MISSING else repr(v)


def _flatten(d: dict, prefix: str = "") -> dict:
    flat = {}
    for k, v in d.items():
        if isinstance(v, dict) and v:
            flat.update(_flatten(v, f"{prefix}{k}."))
        else:
            flat[f"{prefix}{k}"] = v
    return flat
