"""The parsers of outside data as fuzz targets: each takes the bytes of one input, hands them to the parser the way
a user's file or a peer's message reaches it, and lets it return a value or raise the package's InputError (a
MessageError is one). Any other exception, a hang or unbounded memory is a bug; the fuzzer (`python -m perf
fuzz`, atheris) and the suite's replay (tests/test_fuzz_replay.py) both call these.

Seed corpora of valid inputs live in tests/fuzz/corpus/<target>/ (tests/fuzz/make_corpus.py writes them).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

_TMP: Path | None = None


def _tmp() -> Path:
    global _TMP
    if _TMP is None:
        _TMP = Path(tempfile.mkdtemp(prefix="swarmsplat-fuzz-"))
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


TARGETS = {f.__name__: f for f in (g2o, trajectory, image_list, calibration, dataset_yaml, config_yaml, config_set,
                                   swarm_message, link_message, ply_map, dpgo_csv)}


def preload() -> None:
    """Import every parser's module (the fuzzer instruments what is imported while this runs)."""
    import importlib

    for m in ("graph.g2o", "graph.dpgo_csv", "slam.io.trajectory", "slam.io.datasets.folder", "slam.config",
              "slam.flocc.swarm.messages", "slam.run.team_link.messages", "slam.dense.ply"):
        importlib.import_module(f"swarmsplat.{m}")


def corpus_dir(name: str) -> Path:
    """tests/fuzz/corpus/<name> of this checkout."""
    return Path(os.path.realpath(__file__)).parents[1] / "tests" / "fuzz" / "corpus" / name


def expected_errors() -> tuple[type[BaseException], ...]:
    """What a target may raise: the package's InputError (MessageError and CodecError included)."""
    from swarmsplat.kernels.errors import InputError

    return (InputError,)
