"""What robots record, read without a ROS install: ROS 1 `.bag`, ROS 2 bag folders (`.db3` or `.mcap` with
`metadata.yaml`) and bare `.mcap` files, through `rosbags`.

    is_bag(path) -> bool
    load_bag_sequence(path, topics=None) -> BagSequence        one agent (topics found or given)
    load_bag_dataset(path, topics=None) -> MultiAgentDataset   one bag with /robotN/ namespaces, or a folder of bags
    bag_info(path) -> dict; format_info(info) -> str           `swarmsplat bag-info`
    write_bag(sequence, path, fmt="mcap")                      a sequence as a bag (sensor_msgs + CameraInfo)
"""

from __future__ import annotations

from pathlib import Path

from swarmsplat.kernels.errors import InputError

from ..datasets.base import MultiAgentDataset
from .info import bag_info, format_info
from .sequence import BagSequence, open_reader
from .topics import ROLES, TopicChoice, agent_namespaces, choose_topics, parse_topics

__all__ = ["is_bag", "load_bag_sequence", "load_bag_dataset", "bag_info", "format_info", "write_bag",
           "BagSequence", "TopicChoice", "parse_topics", "ROLES"]


def is_bag(path: str | Path) -> bool:
    """A ROS 1 bag, a bare .mcap / .db3 file, or a ROS 2 bag folder (metadata.yaml beside .db3 / .mcap files)."""
    p = Path(path)
    if p.is_file():
        return p.suffix in (".bag", ".mcap", ".db3")
    return p.is_dir() and (p / "metadata.yaml").is_file() and any(
        q.suffix in (".db3", ".mcap") for q in p.iterdir())


def _types(path: Path) -> dict[str, str]:
    reader = open_reader(path, warn=False)  # the sequence's own opening warns
    try:
        return {name: info.msgtype for name, info in reader.topics.items()}
    finally:
        reader.close()


def load_bag_sequence(path: str | Path, topics: dict[str, str] | None = None, **kwargs) -> BagSequence:
    """One agent from a bag. `topics` ({"color": ..., "depth": ..., "info": ..., "odometry": ..., "gt": ...})
    chooses where given; the rest are found (topics.choose_topics). kwargs go to BagSequence (camera=,
    max_diff=, pose_max_diff=, undistort=)."""
    p = Path(path)
    choice = choose_topics(_types(p), topics, str(p))
    return BagSequence(p, choice, **kwargs)


def load_bag_dataset(path: str | Path, topics: dict[str, str] | None = None, **kwargs) -> MultiAgentDataset:
    """A team from one bag whose colour topics differ only in their first namespace (one agent each, named after
    it), or one agent from a bag, or a folder holding several bags (one agent each, in name order)."""
    p = Path(path)
    seqs: list[BagSequence] = []
    try:
        if is_bag(p):
            types = _types(p)
            for ns in agent_namespaces(types, topics):
                seqs.append(BagSequence(p, choose_topics(types, topics, str(p), namespace=ns),
                                        name=ns.strip("/") or p.stem, **kwargs))
        elif p.is_dir():
            bags = sorted(q for q in p.iterdir() if is_bag(q))
            if not bags:
                raise InputError(f"{p}: no bag in this folder (.bag, .mcap, .db3, or ROS 2 bag folders)")
            for b in bags:
                seqs.append(load_bag_sequence(b, topics, **kwargs))
        else:
            raise InputError(f"{p}: not a bag (expected .bag, .mcap, .db3 or a ROS 2 bag folder with metadata.yaml)")
        kinds = {s.is_rgbd for s in seqs}
        if len(kinds) > 1:
            raise InputError(f"{p}: some agents have depth and some do not")
    except BaseException:  # an agent refused: the files of those opened before it are closed too
        for s in seqs:
            s.close()
        raise
    return MultiAgentDataset(root=p, agents=seqs, name=p.stem, kind="rgbd" if kinds.pop() else "mono",
                             meta={"layout": "bag", "topics": [s.topics.as_dict() for s in seqs]})


def write_bag(sequence, path: str | Path, fmt: str = "mcap", **kwargs) -> Path:
    """Write `sequence` as a bag (see write.write_bag)."""
    from .write import write_bag as _write

    return _write(sequence, path, fmt, **kwargs)
