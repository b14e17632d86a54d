"""The generic XFeat-VLAD vocabulary the package ships (registration/place_recognition/vocabularies/), made from
generated worlds only: no image of a user's, of the shared datasets or of the demo's world is in it.

    python -m swarmsplat.slam.synthetic.vocabulary OUT.npz [--clusters 64]

Generates `SEEDS` worlds (the default preset's 3 agents, 60 frames each; seeds the demo, the tests and the
benchmarks do not use), encodes every 5th frame with XFeat at 320 pixels (the team server's coarse width), and
clusters the descriptors with the recogniser's own seeded k-means, so the same code gives the same file. Why
generated worlds serve real images: XFeat's descriptors are generic, and perf/results/placerec-cpu.md measures a
vocabulary from generated worlds against one trained on the searched keyframes.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

SEEDS = (101, 102, 103)
FRAME_STEP = 5
WIDTH = 320


def training_descriptors(seeds=SEEDS, *, frames: int = 60, step: int = FRAME_STEP, width: int = WIDTH,
                         progress: bool = False) -> list[np.ndarray]:
    """One XFeat descriptor array [M, 64] per training image of the generated worlds."""
    import cv2

    from swarmsplat.registration.pair.xfeat import XFeatRegistrar
    from swarmsplat.slam.io.datasets import load_dataset

    from . import GeneratorConfig, generate

    reg = XFeatRegistrar(top_k=512, max_side=640)
    parts = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            root = generate(Path(tmp) / f"w{seed}", GeneratorConfig.preset("default", seed=seed, frames=frames))
            for seq in load_dataset(root).agents:
                for i in range(0, len(seq), step):
                    rgb = seq[i].color
                    if rgb.shape[1] > width:
                        rgb = cv2.resize(rgb, (width, rgb.shape[0] * width // rgb.shape[1]), interpolation=cv2.INTER_AREA)
                    parts.append(np.asarray(reg.encode(rgb).arrays["desc"], np.float32))
            if progress:
                print(f"world seed {seed}: {len(parts)} images so far", flush=True)
    return parts


def train(out: str | Path, *, clusters: int = 64, seeds=SEEDS, progress: bool = False) -> Path:
    from swarmsplat.registration.place_recognition import make_recognizer

    rec = make_recognizer("xfeat-vlad", n_clusters=clusters)
    rec.fit_local(training_descriptors(seeds, progress=progress), seed=0)
    return rec.save(out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m swarmsplat.slam.synthetic.vocabulary", description=__doc__.splitlines()[0])
    p.add_argument("out", help="the .npz to write")
    p.add_argument("--clusters", type=int, default=64, help="vocabulary size K (descriptor = K x 64 floats)")
    args = p.parse_args(argv)
    print(f"wrote {train(args.out, clusters=args.clusters, progress=True)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
