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
    return 0


if __name__ == "__main__":
    sys.exit(main())
