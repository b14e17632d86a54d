"""Reading RGB-D frames from bags (slam.io.bags): frames/s and the memory held while reading, per bag format, with
the folder loader on the same frames as the peer.

The frames are the shared Redwood living-room sequence (640x480; ../shared/data/redwood_livingroom1_211, or
SWARMSPLAT_SHARED_DATA) written as a ROS 1 bag, a ROS 2 MCAP bag and a ROS 2 SQLite bag in a temporary folder;
without the shared data, a generated 320x240 sequence. Measured per format: opening (the index pass), reading
every frame in order (decoded colour and depth, as `swarmsplat run` reads them), reading them in a shuffled order,
and the peak of Python-tracked memory while reading in order (tracemalloc) against one frame's size. The peer
reads the same frames from the folder (JPEG colour, PNG depth). Target: >= 200 frames/s of 640x480 RGB-D.
"""

from __future__ import annotations

import os
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

DESCRIPTION = "bag reading, frames/s and memory held, ROS 1 / MCAP / SQLite bags (peer: the folder loader)"
REDWOOD = Path(os.environ.get("SWARMSPLAT_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")) \
    / "redwood_livingroom1_211"


def _source(tmp: Path, quick: bool):
    from swarmsplat.slam.io.datasets import load_sequence

    if REDWOOD.is_dir():
        return load_sequence(REDWOOD), "redwood_livingroom1_211"
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    root = generate(tmp / "gen", GeneratorConfig.preset("default", agents=1, frames=60 if quick else 200))
    return load_sequence(root / "agent_0"), "generated"


def _read_all(seq, order) -> float:
    t0 = time.perf_counter()
    for i in order:
        f = seq[int(i)]
        assert f.color is not None
    return time.perf_counter() - t0


def run(*, backends: list[str], device: str, quick: bool) -> dict:
    from swarmsplat.slam.io.bags import load_bag_sequence, write_bag

    rows = []
    with tempfile.TemporaryDirectory(prefix="perf-bags-") as tmp:
        tmp = Path(tmp)
        seq, name = _source(tmp, quick)
        n = min(len(seq), 60 if quick else len(seq))
        order = np.arange(n)
        shuffled = np.random.default_rng(0).permutation(n)
        frame_mb = seq.camera.width * seq.camera.height * 7 / 1e6  # RGB uint8 + float32 depth
        peer_s = min(_read_all(seq, order) for _ in range(2))
        for fmt, fname in (("ros1", "seq.bag"), ("mcap", "seq_mcap"), ("db3", "seq_db3")):
            path = write_bag(seq, tmp / fname, fmt, frames=n)
            t0 = time.perf_counter()
            bag = load_bag_sequence(path)
            open_s = time.perf_counter() - t0
            _read_all(bag, order)  # warm the page cache as the peer's first pass did
            tracemalloc.start()
            in_order = _read_all(bag, order)
            _, peak = tracemalloc.get_traced_memory()
            tracemalloc.stop()
            shuffled_s = _read_all(bag, shuffled)
            bag.close()
            rows.append({"format": fmt, "frames": n, "image": f"{seq.camera.width}x{seq.camera.height}",
                         "open_s": round(open_s, 3), "fps_in_order": round(n / in_order, 1),
                         "fps_shuffled": round(n / shuffled_s, 1), "peak_mb": round(peak / 1e6, 1),
                         "frame_mb": round(frame_mb, 2), "peer_fps": round(n / peer_s, 1),
                         "speedup": round(peer_s / in_order, 2)})
    return {"rows": rows, "columns": list(rows[0]),
            "notes": [f"frames: {name}, the first {n}; bags written by slam.io.bags.write_bag (raw rgb8, 16UC1 "
                      "depth when the source is whole millimetres)",
                      "fps_in_order: every frame in turn (one stream); fps_shuffled: a random order (a seek per "
                      "frame); both after one warm-up pass; open_s: the index pass",
                      "peak_mb: Python-tracked memory (tracemalloc) at its peak while reading in order",
                      "peer: the folder loader reading the same frames (JPEG / PNG decode); speedup = peer time / "
                      "in-order bag time"]}
