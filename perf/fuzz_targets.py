"""The parsers of outside data as fuzz targets: each takes the bytes of one input, hands them to the parser the way
a user's file or a peer's message reaches it, and lets it return a value or raise the package's InputError (a
MessageError is one). Any other exception, a hang or unbounded memory is a bug; the fuzzer (`python -m perf
fuzz`, atheris) and the suite's replay (tests/test_fuzz_replay.py) both call these.

Seed corpora of valid inputs live in tests/fuzz/corpus/<target>/ (tests/fuzz/make_corpus.py writes them).
"""

from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path

_TMP: Path | None = None


def _tmp() -> Path:
    """The targets' scratch folder, in memory where the system has one (/dev/shm): each input is written to a
    file there, and writing a file on a disk-backed /tmp can cost milliseconds, more than most parsers take."""
    global _TMP
    if _TMP is None:
        shm = "/dev/shm"
        where = shm if os.path.isdir(shm) and os.access(shm, os.W_OK) else None
        _TMP = Path(tempfile.mkdtemp(prefix="swarmsplat-fuzz-", dir=where))
    return _TMP


def _file(data: bytes, name: str) -> Path:
    p = _tmp() / name
    p.write_bytes(data)
    return p


def g2o(data: bytes) -> None:
    from swarmsplat.graph.g2o import read_g2o

    read_g2o(_file(data, "graph.g2o"))


def trajectory(data: bytes) -> None:
    """The first byte picks the format (TUM, KITTI, EuRoC CSV, Redwood .log, auto-detect); the rest is the file."""
    from swarmsplat.slam.io.trajectory import read_trajectory

    fmt = ("tum", "kitti", "euroc", "log", "auto")[data[0] % 5] if data else "auto"
    read_trajectory(_file(data[1:], "poses.txt"), fmt)


def image_list(data: bytes) -> None:
    from swarmsplat.slam.io.datasets.folder import read_image_list

    _file(b"", "exists.png")
    read_image_list(_file(data, "rgb.txt"))


def calibration(data: bytes) -> None:
    from swarmsplat.slam.io.datasets.folder import read_calibration

    read_calibration(_file(data, "calibration.yaml"), need_depth_scale=True)


def dataset_yaml(data: bytes) -> None:
    from swarmsplat.slam.io.datasets.folder import load_folder_dataset

    root = _tmp() / "team"
    root.mkdir(exist_ok=True)
    (root / "dataset.yaml").write_bytes(data)
    load_folder_dataset(root)


def config_yaml(data: bytes) -> None:
    from swarmsplat.slam.config import SlamConfig

    SlamConfig.from_yaml(_file(data, "config.yaml"))


def config_set(data: bytes) -> None:
    """`--set KEY=VALUE` items, one per line: the value read as YAML and applied to the config tree by
    SlamConfig.override, the validation every --set goes through (slam.cli.config_flags.load_config)."""
    import yaml

    from swarmsplat.slam.config import SlamConfig

    cfg = SlamConfig()
    for item in data.decode("utf-8", errors="replace").splitlines()[:8]:
        key, _, text = item.partition("=")
        try:
            value = yaml.safe_load(text) if text.strip() else None
        except yaml.YAMLError:
            value = text
        update = value
        for part in reversed(key.strip().split(".")):
            update = {part: update}
        cfg = cfg.override(update if isinstance(update, dict) else {}, where=f"--set {item}")


def swarm_message(data: bytes) -> None:
    from swarmsplat.slam.flocc.swarm.messages import SWARM

    SWARM.decode(data)


def link_message(data: bytes) -> None:
    from swarmsplat.slam.run.team_link.messages import LINK

    LINK.decode(data)


def ply_map(data: bytes) -> None:
    from swarmsplat.slam.dense.ply import load_ply

    load_ply(_file(data, "map.ply"))


def dpgo_csv(data: bytes) -> None:
    """One robot's measurements.csv (robot 0 of a one-robot team)."""
    from swarmsplat.graph.dpgo_csv import read_measurements

    root = _tmp() / "dpgo"
    (root / "robot0").mkdir(parents=True, exist_ok=True)
    (root / "robot0" / "measurements.csv").write_bytes(data)
    read_measurements(root)


_MEMO: dict[str, object] = {}
_PATCHES: list[tuple[object, str, object]] = []  # (module, name, memoised function), made on first use


@contextmanager
def _memoised_rosbags():
    """rosbags turns a bag's message definitions into Python on every open: it parses them, execs the generated
    classes into a fresh type store and compiles a deserialiser per type on first use (~20 ms an open; a bag is
    opened once per agent and once more to list its topics); and it reads each ROS 2 topic's QoS profiles with a
    new ruamel YAML loader (~0.4 ms a topic, half of an MCAP input's time). Both are pure functions of text that
    most fuzz inputs copy from the seeds, so while a bag target runs they are memoised by that text (the type store
    by the parsed types; at most 64 type stores and 256 texts of each kind). A text never seen is parsed, generated
    and compiled as on any open, and its errors are raised every time; everything else (the readers, the index,
    every record and every deserialisation) runs per input. The default type store slam.io.bags hands each open
    (ROS 2 Humble's or ROS 1 Noetic's, only read) is built once, not from its hundreds of types on every open.
    Outside the targets' calls rosbags is as imported."""
    if not _PATCHES:
        _PATCHES.extend(_rosbags_memos())
    saved = [(m, n, getattr(m, n)) for m, n, _ in _PATCHES]
    for m, n, f in _PATCHES:
        setattr(m, n, f)
    try:
        yield
    finally:
        for m, n, f in saved:
            setattr(m, n, f)


def _rosbags_memos() -> list[tuple[object, str, object]]:
    import functools

    import rosbags.highlevel.anyreader as ar
    import rosbags.rosbag2.storage_mcap as mcap
    import rosbags.rosbag2.storage_sqlite3 as sqlite
    import rosbags.typesys as typesys
    from rosbags.typesys.store import Typestore

    class MemoStore(Typestore):
        def register(self, typs) -> None:
            key = repr(typs)
            done = _MEMO.get(key)
            if done is None:
                super().register(typs)
                if len(_MEMO) < 64:
                    _MEMO[key] = self
                return
            self.fielddefs, self.types, self.cache = done.fielddefs, done.types, done.cache

    real, real_qos = ar.get_typestore, mcap.parse_qos
    named = functools.lru_cache(maxsize=4)(real)
    qos_of_text = functools.lru_cache(maxsize=256)(real_qos)

    def reader_store(name):  # AnyReader's own: EMPTY, then the bag's types registered
        store = real(name)
        if name == ar.Stores.EMPTY:
            store.__class__ = MemoStore
        return store

    def parse_qos(profiles):
        return list(qos_of_text(profiles)) if isinstance(profiles, str) else real_qos(profiles)

    return [(ar, "get_typestore", reader_store),
            (typesys, "get_typestore", lambda name: real(name) if name == typesys.Stores.EMPTY else named(name)),
            (ar, "get_types_from_msg", functools.lru_cache(maxsize=256)(ar.get_types_from_msg)),
            (ar, "get_types_from_idl", functools.lru_cache(maxsize=256)(ar.get_types_from_idl)),
            (mcap, "parse_qos", parse_qos), (sqlite, "parse_qos", parse_qos)]


def _bag(data: bytes, name: str) -> None:
    """A bag file as `swarmsplat run BAG` opens it (slam.io.datasets.load_dataset: topics found, the bag indexed,
    one agent per /robotN/ namespace), then at most four of each agent's frames decoded (the first two from the
    stream, the last and the first again, each a restart from its record time); the readers closed after."""
    import warnings

    from swarmsplat.slam.io.datasets import load_dataset

    path = _file(data, name)
    with warnings.catch_warnings(), _memoised_rosbags():  # a bag cut short warns and is read: not an error
        warnings.simplefilter("ignore")
        ds = load_dataset(path)
        try:
            for seq in ds.agents:
                for i in (0, 1, -1, 0)[: min(len(seq), 4)]:
                    seq[i]
        finally:
            for seq in ds.agents:
                seq.close()


def ros1_bag(data: bytes) -> None:
    """A ROS 1 .bag (rosbags' reader, or slam.io.bags.truncated's index rebuild for a bag cut short)."""
    _bag(data, "input.bag")


def ros2_sqlite(data: bytes) -> None:
    """A ROS 2 bag's SQLite storage file, bare (.db3, no metadata.yaml)."""
    _bag(data, "input.db3")


def mcap_bag(data: bytes) -> None:
    """A bare .mcap file (a ROS 2 bag's MCAP storage; read to its last complete record when cut short)."""
    _bag(data, "input.mcap")


TARGETS = {f.__name__: f for f in (g2o, trajectory, image_list, calibration, dataset_yaml, config_yaml, config_set,
                                   swarm_message, link_message, ply_map, dpgo_csv, ros1_bag, ros2_sqlite, mcap_bag)}


# What the fuzzer instruments for coverage: the package, and rosbags, whose readers parse the bags' records under
# slam.io.bags (the bag targets would be blind to most of a bag's format without it).
INSTRUMENT = ["swarmsplat", "rosbags"]


def preload() -> None:
    """Import every parser's module (the fuzzer instruments what is imported while this runs)."""
    import importlib

    for m in ("graph.g2o", "graph.dpgo_csv", "slam.io.trajectory", "slam.io.datasets.folder", "slam.config",
              "slam.flocc.swarm.messages", "slam.run.team_link.messages", "slam.dense.ply", "slam.io.datasets",
              "slam.io.bags", "slam.io.bags.truncated"):
        importlib.import_module(f"swarmsplat.{m}")
    for m in ("highlevel", "rosbag1", "rosbag2", "rosbag2.storage_mcap", "rosbag2.storage_sqlite3", "typesys",
              "typesys.stores.empty", "typesys.stores.ros1_noetic", "typesys.stores.ros2_humble"):
        importlib.import_module(f"rosbags.{m}")


def corpus_dir(name: str) -> Path:
    """tests/fuzz/corpus/<name> of this checkout."""
    return Path(os.path.realpath(__file__)).parents[1] / "tests" / "fuzz" / "corpus" / name


def expected_errors() -> tuple[type[BaseException], ...]:
    """What a target may raise: the package's InputError (MessageError and CodecError included)."""
    from swarmsplat.kernels.errors import InputError

    return (InputError,)
