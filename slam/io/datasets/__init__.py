"""Dataset loaders: our folder format plus the public layouts users already have (TUM RGB-D, Redwood /
ICL-NUIM, Replica and Multiagent Replica, EuRoC, ScanNet exports, 7-Scenes) and what robots record (ROS 1 / ROS 2
bags and MCAP, slam.io.bags). Every loader returns lazily loading `Sequence`s; a `MultiAgentDataset` groups one
per agent.

    load_sequence(path, fmt="auto") -> Sequence
    load_dataset(path, fmt="auto")  -> MultiAgentDataset   (a single sequence becomes a one-agent team)

A bag takes `topics={"color": ..., "depth": ..., "info": ..., "odometry": ..., "gt": ...}` (any subset; the rest
are found) in place of `fmt`.
"""

from __future__ import annotations

from pathlib import Path

from swarmsplat.kernels.errors import InputError
from swarmsplat.kernels.fileio import is_file

from ._sequence import ImageSequence
from .associate import associate_unique, match_nearest
from .base import Frame, MultiAgentDataset, Sequence
from .euroc import is_euroc_sequence, load_euroc_sequence
from .folder import is_folder_sequence, load_folder_dataset, load_folder_sequence
from .redwood import is_redwood_sequence, load_redwood_sequence
from .replica import is_replica_sequence, load_replica_sequence
from .scannet import is_scannet_sequence, load_scannet_sequence
from .sevenscenes import is_sevenscenes_sequence, load_sevenscenes_sequence
from .tum import is_tum_sequence, load_tum_sequence

__all__ = [
    "Frame", "Sequence", "MultiAgentDataset", "ImageSequence", "FORMATS",
    "load_sequence", "load_dataset", "detect_sequence_format",
    "load_folder_sequence", "load_folder_dataset", "load_tum_sequence", "load_redwood_sequence",
    "load_replica_sequence", "load_euroc_sequence", "load_scannet_sequence", "load_sevenscenes_sequence",
    "match_nearest", "associate_unique",
]

# Checked in this order: our format first (it is TUM-like but carries calibration.yaml); ScanNet (color/ depth/
# intrinsic/) before Redwood (color/ depth/ and a .log).
_DETECT = {
    "folder": is_folder_sequence,
    "tum": is_tum_sequence,
    "replica": is_replica_sequence,
    "euroc": is_euroc_sequence,
    "scannet": is_scannet_sequence,
    "redwood": is_redwood_sequence,
    "7scenes": is_sevenscenes_sequence,
}
_LOAD = {
    "folder": load_folder_sequence,
    "tum": load_tum_sequence,
    "replica": load_replica_sequence,
    "euroc": load_euroc_sequence,
    "scannet": load_scannet_sequence,
    "redwood": load_redwood_sequence,
    "7scenes": load_sevenscenes_sequence,
}
FORMATS = tuple(_DETECT)

_LAYOUTS_HELP = ("our format (calibration.yaml + rgb.txt), TUM RGB-D (rgb.txt + depth.txt), Replica "
                 "(results/ + traj.txt), EuRoC (mav0/cam0/data.csv), ScanNet (color/ + depth/ + intrinsic/), "
                 "Redwood (color/ + depth/ + .log), 7-Scenes (frame-NNNNNN.color.png + .depth.png) or a bag "
                 "(.bag, .mcap, .db3, ROS 2 bag folder)")


def _check(path: str | Path, fmt: str) -> tuple[Path, str]:
    p = Path(path)
    if not _exists(p):
        raise InputError(f"dataset path not found: {p}")
    if not p.is_dir():
        raise InputError(f"dataset path is not a folder or a bag (.bag, .mcap, .db3): {p}")
    fmt = (fmt or "auto").lower()
    if fmt != "auto" and fmt not in FORMATS:
        raise InputError(f"unknown dataset format {fmt!r}; expected one of {', '.join(FORMATS)}, bag or auto")
    return p, fmt


def detect_sequence_format(path: str | Path) -> str | None:
    """The layout name of a single-sequence folder, or None when no loader recognises it."""
    p = Path(path)
    for name, test in _DETECT.items():
        if test(p):
            return name
    return None


def _load_agent_folder(folder: Path) -> ImageSequence:
    """An agent folder named by dataset.yaml, in any single-sequence layout (our format first)."""
    if is_folder_sequence(folder):
        return load_folder_sequence(folder)
    fmt = detect_sequence_format(folder)
    if fmt is None:
        raise InputError(f"{folder}: not a sequence in any layout read here; expected {_LAYOUTS_HELP}")
    seq = _LOAD[fmt](folder)
    seq.name = folder.name
    return seq


def _exists(path: str | Path) -> bool:
    """Path.exists(), a name the system refuses (too long, ...) an InputError naming it."""
    is_file(path, "dataset path")
    return Path(path).exists()


def _bag_kind(path: str | Path, fmt: str) -> bool:
    """Is `path` a bag (or, for a team, a folder of bags)? fmt "bag" insists; another layout name refuses."""
    from swarmsplat.slam.io.bags import is_bag

    p = Path(path)
    bag = is_bag(p) or (p.is_dir() and not (p / "dataset.yaml").is_file() and detect_sequence_format(p) is None
                        and any(is_bag(q) for q in p.iterdir()))
    if (fmt or "auto").lower() == "bag" and not bag:
        raise InputError(f"{p}: not a bag (expected .bag, .mcap, .db3 or a ROS 2 bag folder with metadata.yaml)")
    return bag and (fmt or "auto").lower() in ("auto", "bag")


def load_sequence(path: str | Path, fmt: str = "auto", **kwargs) -> ImageSequence:
    """Load one sequence; `fmt` is one of FORMATS, "bag" or "auto". Extra keyword arguments go to the loader
    (e.g. `camera=` for TUM/Redwood/Replica/7-Scenes, `undistort=` for EuRoC and bags, `topics=` for bags)."""
    if _exists(path) and _bag_kind(path, fmt):
        from swarmsplat.slam.io.bags import load_bag_sequence

        return load_bag_sequence(path, **kwargs)
    kwargs.pop("topics", None)
    p, fmt = _check(path, fmt)
    if fmt == "auto":
        fmt = detect_sequence_format(p)
        if fmt is None:
            raise InputError(f"{p}: not a recognised sequence folder; expected {_LAYOUTS_HELP}")
    return _LOAD[fmt](p, **kwargs)


def load_dataset(path: str | Path, fmt: str = "auto", **kwargs) -> MultiAgentDataset:
    """Load a team: a root with dataset.yaml (our format), a single sequence (one agent), or a folder whose
    sub-folders are sequences of one layout (Multiagent Replica, a set of EuRoC runs, a 7-Scenes scene's seq-NN
    folders), agents in name order; or a bag (one agent, or one per /robotN/ namespace), or a folder of bags."""
    if _exists(path) and _bag_kind(path, fmt):
        from swarmsplat.slam.io.bags import load_bag_dataset

        return load_bag_dataset(path, **kwargs)
    kwargs.pop("topics", None)
    p, fmt = _check(path, fmt)
    if (p / "dataset.yaml").is_file() and fmt in ("auto", "folder"):
        return load_folder_dataset(p, load_agent=_load_agent_folder)
    own = detect_sequence_format(p) if fmt == "auto" else (fmt if _DETECT[fmt](p) else None)
    if own is not None:
        seq = _LOAD[own](p, **kwargs)
        return MultiAgentDataset(root=p, agents=[seq], name=seq.name, kind="rgbd" if seq.is_rgbd else "mono",
                                 meta={"layout": own})
    subs = [(d, detect_sequence_format(d)) for d in sorted(p.iterdir()) if d.is_dir()]
    subs = [(d, f) for d, f in subs if f is not None and (fmt == "auto" or f == fmt)]
    if not subs:
        raise InputError(f"{p}: no dataset.yaml, and neither the folder nor its sub-folders are sequences; "
                         f"expected {_LAYOUTS_HELP}")
    layouts = sorted({f for _, f in subs})
    if len(layouts) > 1:
        raise InputError(f"{p}: sub-folders mix sequence layouts ({', '.join(layouts)}); pass fmt= to choose one")
    seqs = [_LOAD[f](d, **kwargs) for d, f in subs]
    kinds = {s.is_rgbd for s in seqs}
    if len(kinds) > 1:
        raise InputError(f"{p}: sub-folders mix RGB-D and monocular sequences")
    return MultiAgentDataset(root=p, agents=seqs, name=p.name, kind="rgbd" if kinds.pop() else "mono",
                             meta={"layout": layouts[0]})
