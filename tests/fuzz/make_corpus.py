"""Writes the fuzzers' seed corpora, tests/fuzz/corpus/<target>/: a few small valid inputs per parser of
perf/fuzz_targets.py (run from the repository: `python tests/fuzz/make_corpus.py`; the files are committed, so
the fuzz replay in the suite needs nothing else)."""

from __future__ import annotations

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def _write(target: str, name: str, data: bytes) -> None:
    d = HERE / "corpus" / target
    d.mkdir(parents=True, exist_ok=True)
    (d / name).write_bytes(data)


def main() -> int:
    import torch

    from swarmsplat.slam.dense.gaussian_map import GaussianParams
    from swarmsplat.slam.dense.ply import save_ply
    from swarmsplat.slam.flocc.swarm import messages as sm
    from swarmsplat.slam.run.team_link import messages as lm

    info3 = " ".join(["1 0 0 0 0 0", "1 0 0 0 0", "1 0 0 0", "1 0 0", "1 0", "1"])
    _write("g2o", "se3.g2o", (f"VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
                              f"EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {info3}\n").encode())
    _write("g2o", "se2.g2o", b"VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0.1\nEDGE_SE2 0 1 1 0 0.1 1 0 0 1 0 1\n")
    _write("trajectory", "tum.txt", b"\x00# t x y z qx qy qz qw\n0.0 0 0 0 0 0 0 1\n0.1 0.1 0 0 0 0 0 1\n")
    _write("trajectory", "kitti.txt", b"\x011 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0.1 0 1 0 0 0 0 1 0\n")
    _write("trajectory", "euroc.csv", b"\x02#timestamp,p_x,p_y,p_z,q_w,q_x,q_y,q_z\n0,0,0,0,1,0,0,0\n"
                                      b"100000000,0.1,0,0,1,0,0,0\n")
    _write("trajectory", "redwood.log", b"\x030 0 1\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    _write("image_list", "rgb.txt", b"# timestamp filename\n0.0 exists.png\n0.1 exists.png\n")
    _write("calibration", "calibration.yaml", b"fx: 525.0\nfy: 525.0\ncx: 319.5\ncy: 239.5\nwidth: 640\n"
                                               b"height: 480\ndepth_scale: 5000.0\n")
    _write("dataset_yaml", "dataset.yaml", b"name: team\nkind: rgbd\nagents: [agent_0, agent_1]\n")
    _write("config_yaml", "config.yaml", b"mapping:\n  iterations: 5\nserver:\n  top_k: 3\n")
    _write("config_set", "sets.txt", b"server.top_k=4\nloop_closure.descriptor=thumbnail\nserver.tau_sim=null\n")
    _write("swarm_message", "hello.bin", sm.SWARM.encode(sm.Hello(tick=3, n_keyframes=2, have_desc={"1": 4}), 1, 7))
    _write("swarm_message", "estimate.bin", sm.SWARM.encode(sm.DistributedEstimate(root=97, blob=_relative_estimate()),
                                                            1, 8))
    _write("swarm_message", "estimate_sparse.bin", sm.SWARM.encode(
        sm.DistributedEstimate(root=97, blob=_relative_estimate(sparse=True)), 1, 9))
    _write("link_message", "join.bin", lm.LINK.encode(lm.Join(mid=1, name="a", camera=[525.0, 525.0, 319.5, 239.5,
                                                                                      640, 480], config="x"), 1, 1))
    g = torch.Generator().manual_seed(0)
    params = GaussianParams.from_points(torch.rand(4, 3, generator=g), torch.rand(4, 3, generator=g),
                                        torch.full((4,), 0.01))
    (HERE / "corpus" / "ply_map").mkdir(parents=True, exist_ok=True)
    save_ply(HERE / "corpus" / "ply_map" / "map.ply", params)
    _write("dpgo_csv", "measurements.csv",
           b"robot_src,pose_src,robot_dst,pose_dst,qx,qy,qz,qw,tx,ty,tz,kappa,tau,is_known_inlier,weight\n"
           b"0,0,0,1,0,0,0,1,1,0,0,100,100,1,1\n0,1,0,2,0,0,0,1,1,0,0,100,100,1,1\n")
    _bags()
    return 0


def _relative_estimate(sparse: bool = False):
    """A distributed-solver estimate with two separator poses as float16 twists from stamp 3, a scale and a weight
    (`sparse`: eleven poses, two of them moved, after their bit mask)."""
    import numpy as np

    from swarmsplat.graph.distributed.messages import FLAG_DELTA, FLAG_SPARSE, Estimate

    delta = np.array([[0.01, 0, 0, 0.1, 0, 0], [0, 0.02, 0, 0, 0.2, 0]])
    if sparse:
        delta = np.zeros((11, 6))
        delta[[3, 9]] = [[0.01, 0, 0, 0.1, 0, 0], [0, 0.02, 0, 0, 0.2, 0]]
    m = Estimate(97, 98, 4, scales=np.array([1.25]), weights=np.array([1.0]),
                 flags=FLAG_DELTA | (FLAG_SPARSE if sparse else 0), base=3, ack=2, delta=delta)
    return np.frombuffer(m.to_bytes(), np.uint8)


class _Tiny:
    """A sequence of `n` frames of 8x6 pixels (the least a bag needs: colour, depth, a camera, poses) for the bag
    seeds; write_bag (slam.io.bags.write) records it as a camera driver would."""

    def __init__(self, n: int = 2, odometry: bool = False, scale: float = 1000.0):
        import numpy as np

        from swarmsplat.kernels.camera import PinholeCamera

        rng = np.random.default_rng(n)
        self.camera, self.depth_scale, self.is_rgbd = PinholeCamera(8.0, 8.0, 4.0, 3.0, 8, 6), scale, True
        self.t = 1.0 + 0.1 * np.arange(n)
        self.color = rng.integers(0, 256, (n, 6, 8, 3), dtype=np.uint8)
        self.depth = (rng.integers(1, 4000, (n, 6, 8)) / 1000.0).astype(np.float32)
        self.gt_poses = np.tile(np.eye(4), (n, 1, 1))
        self.gt_poses[:, 0, 3] = self.t
        self.odometry = self.gt_poses.copy() if odometry else None

    def __len__(self) -> int:
        return len(self.t)

    def __getitem__(self, i: int):
        from swarmsplat.slam.io.datasets.base import Frame

        return Frame(i, float(self.t[i]), self.color[i], self.depth[i], self.gt_poses[i],
                     None if self.odometry is None else self.odometry[i])


def _ros1_again(src: Path, dst: Path, compression: str | None = None, chunk: int | None = None) -> None:
    """`src` (a ROS 1 bag) recorded again with compressed chunks ("bz2", "lz4") or chunks of about `chunk` bytes."""
    from rosbags.rosbag1 import Reader, Writer

    with Reader(src) as r, Writer(dst) as w:
        if compression:
            w.close()  # set_compression needs an unopened writer
            dst.unlink()
            w.set_compression(Writer.CompressionFormat[compression.upper()])
            w.open()
        if chunk:
            w.chunk_threshold = chunk
        conns = {c.id: w.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data, md5sum=c.digest)
                 for c in r.connections}
        for c, t, raw in r.messages():
            w.write(conns[c.id], t, raw)


def _mcap_again(src: Path, dst: Path, compression: str = "", chunk: int = 1 << 20) -> None:
    """`src` (an MCAP file) written again by the mcap library, with chunks of about `chunk` bytes compressed by
    "zstd", "lz4" or nothing."""
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    with src.open("rb") as f, dst.open("wb") as out:
        w = Writer(out, chunk_size=chunk, compression=CompressionType[(compression or "none").upper()])
        w.start(profile="ros2", library="swarmsplat-fuzz-seed")
        reader = make_reader(f)
        summary = reader.get_summary()
        schemas = {k: w.register_schema(s.name, s.encoding, s.data) for k, s in summary.schemas.items()}
        chans = {k: w.register_channel(c.topic, c.message_encoding, schemas[c.schema_id], c.metadata)
                 for k, c in summary.channels.items()}
        for _, ch, m in reader.iter_messages():
            w.add_message(chans[ch.id], m.log_time, m.data, m.publish_time, m.sequence)
        w.finish()


def _bags() -> None:
    """Tiny valid bags of each format (a few KB: two or three 8x6 frames) and a few variants: compressed colour
    with float depth and odometry, a team of two namespaces, compressed chunks, a recording cut short."""
    import shutil
    import sqlite3
    import tempfile

    from swarmsplat.slam.io.bags import write_bag

    def save(target: str, name: str, src: Path) -> Path:
        d = HERE / "corpus" / target
        d.mkdir(parents=True, exist_ok=True)
        shutil.copy(src, d / name)
        return d / name

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        variants = {"rgbd": (_Tiny(2), {}),
                    "png_odom": (_Tiny(3, odometry=True, scale=5000.0), {"color": "png"}),
                    "team": ({"/robot1/camera": _Tiny(1), "/robot2/camera": _Tiny(1)}, {})}
        for name, (seq, kw) in variants.items():
            write_bag(seq, tmp / f"{name}.bag", "ros1", **kw)
            save("ros1_bag", f"{name}.bag", tmp / f"{name}.bag")
            folder = write_bag(seq, tmp / f"{name}_mcap", "mcap", **kw)
            save("mcap_bag", f"{name}.mcap", folder / f"{name}_mcap.mcap")
            folder = write_bag(seq, tmp / f"{name}_db3", "db3", **kw)
            db = shutil.copy(folder / f"{name}_db3.db3", tmp / f"{name}.db3")
            con = sqlite3.connect(db)  # 512-byte pages (from 4096): a smaller seed
            con.execute("PRAGMA journal_mode=DELETE")
            con.execute("PRAGMA page_size=512")
            con.execute("VACUUM")
            con.close()
            save("ros2_sqlite", f"{name}.db3", db)
        longer = write_bag(_Tiny(4), tmp / "long.bag", "ros1")
        _ros1_again(longer, tmp / "bz2.bag", "bz2")
        save("ros1_bag", "bz2.bag", tmp / "bz2.bag")
        _ros1_again(longer, tmp / "lz4.bag", "lz4")
        save("ros1_bag", "lz4.bag", tmp / "lz4.bag")
        _ros1_again(longer, tmp / "chunks.bag", chunk=256)
        data = (tmp / "chunks.bag").read_bytes()  # cut inside its last chunk: the index rebuilt from the rest
        (tmp / "cut.bag").write_bytes(data[: len(data) * 3 // 4])
        save("ros1_bag", "cut.bag", tmp / "cut.bag")
        src = write_bag(_Tiny(4), tmp / "long_mcap", "mcap") / "long_mcap.mcap"
        for comp in ("zstd", "lz4"):
            _mcap_again(src, tmp / f"{comp}.mcap", comp, chunk=1024)
            save("mcap_bag", f"{comp}.mcap", tmp / f"{comp}.mcap")
        data = (tmp / "zstd.mcap").read_bytes()  # no summary, no footer: read to the last complete record
        (tmp / "cut.mcap").write_bytes(data[: len(data) * 2 // 3])
        save("mcap_bag", "cut.mcap", tmp / "cut.mcap")


if __name__ == "__main__":
    sys.exit(main())
