"""Data side of the Fig. 5 study (perf/flocc_fig5.py): the generated monocular team rendered lazily, keyframes by
odometry path length, and the caches that let every keyframe spacing reuse one encoding per frame and one
registration per frame pair (each spacing is charged the measured time of the calls it uses)."""

from __future__ import annotations

import os
import time

import numpy as np

DEFAULT_ROWS = ("classical", "xfeat", "lightglue-disk", "mast3r")  # learned rows say "not available" without package


class Scene:
    """Ground truth, odometry and lazily rendered noisy images of a generated monocular team (robots 'a', 'b', ..)."""

    def __init__(self, cfg, seed: int):  # cfg: perf.flocc_fig5.StudyConfig
        from swarmsplat.slam.synthetic import GeneratorConfig, agent_poses, dataset_camera, generate_world
        from swarmsplat.slam.synthetic.config import MotionConfig
        from swarmsplat.slam.synthetic.mono import drifting_odometry

        self.gen = GeneratorConfig.build(name="fig5", seed=seed, agents=cfg.agents, frames=cfg.frames,
                                         width=cfg.width, height=cfg.height, mono=True,
                                         motion=MotionConfig(loop_turns=cfg.loop_turns))
        self.world = generate_world(self.gen.seed, self.gen.world)
        self.camera = dataset_camera(self.gen)
        self.robots = [chr(ord("a") + r) for r in range(cfg.agents)]
        self.gt = dict(zip(self.robots, agent_poses(self.world, self.gen)))  # robot -> [N, 4, 4] T_world_cam
        # the writer's odometry generator and seeds: the same odometry.txt `swarmsplat generate --mono` writes
        self.odometry = {c: drifting_odometry(self.gt[c], self.gen.odometry, np.random.default_rng([seed, r, 5]))
                         for r, c in enumerate(self.robots)}
        self._images: dict[tuple[str, int], np.ndarray] = {}
        self.render_s = 0.0

    def render(self, robot: str, frames) -> None:
        """Render (and keep) the images of `frames` of `robot` not rendered yet, in batches."""
        from swarmsplat.slam.synthetic.noise import frame_rng, noisy_color
        from swarmsplat.slam.synthetic.render import cast

        todo = [f for f in frames if (robot, f) not in self._images]
        t0 = time.perf_counter()
        r = self.robots.index(robot)
        for s in range(0, len(todo), 8):
            batch = todo[s:s + 8]
            hits = cast(self.world, self.gt[robot][batch], self.camera)
            for j, f in enumerate(batch):
                rng = frame_rng(self.gen.seed, r, f)  # the writer's per-frame noise: the same pixels as the files
                self._images[(robot, f)] = noisy_color(hits.color[j], self.gen.color_noise, rng)
        self.render_s += time.perf_counter() - t0

    def image(self, robot: str, frame: int) -> np.ndarray:
        if (robot, frame) not in self._images:
            self.render(robot, [frame])
        return self._images[(robot, frame)]


def keyframes(odometry: np.ndarray, spacing: float) -> list[int]:
    """Frame indices where the odometry path length first reaches 0, d, 2d, ... (frame 0 always)."""
    if spacing <= 0:
        from swarmsplat.kernels.errors import InputError

        raise InputError(f"keyframe spacing must be > 0 m, got {spacing}")
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(odometry[:, :3, 3], axis=0), axis=1))]
    marks = np.arange(0.0, s[-1] + 1e-9, spacing)
    return sorted(set(int(np.searchsorted(s, m - 1e-9)) for m in marks))


class FrameCache:
    """Encodings per frame and registrations per frame pair, computed once with their measured wall time."""

    def __init__(self, registrar, scene: Scene):
        self.reg, self.scene = registrar, scene
        self.enc: dict[tuple[str, int], object] = {}
        self.enc_s: dict[tuple[str, int], float] = {}
        self.pairs: dict[tuple, object] = {}
        self.pair_s: dict[tuple, float] = {}

    def encoding(self, robot: str, frame: int):
        k = (robot, frame)
        if k not in self.enc:
            t0 = time.perf_counter()
            self.enc[k] = self.reg.encode(self.scene.image(robot, frame))
            self.enc_s[k] = time.perf_counter() - t0
        return self.enc[k]


class CachedRegistrar:
    """A registrar for one spacing's LoopFrontend whose `register` reuses the frame-pair cache (keys are the
    frames behind the encodings the front-end was given); `used` records which cached calls this spacing made."""

    def __init__(self, cache: FrameCache, frame_of_encoding: dict[int, tuple[str, int]]):
        self.cache, self.frame_of = cache, frame_of_encoding
        self.used: set = set()
        self.name = cache.reg.name

    def encode(self, image):  # never called: every keyframe's encoding is put into the front-end first
        raise RuntimeError("flocc_fig5: encodings come from the frame cache")

    def register(self, enc_q, enc_m, cam_q, cam_m=None):
        k = (self.frame_of[id(enc_q)], self.frame_of[id(enc_m)])
        c = self.cache
        if k not in c.pairs:
            t0 = time.perf_counter()
            c.pairs[k] = c.reg.register(enc_q, enc_m, cam_q, cam_m)
            c.pair_s[k] = time.perf_counter() - t0
        self.used.add(k)
        return c.pairs[k]


def registrars(names=DEFAULT_ROWS) -> list[tuple[str, object | None, str]]:
    """(row name, registrar or None, why not available) for the backends `names` of the study: classical rows
    ('classical', 'classical-orb') first, then the learned ones asked for."""
    from swarmsplat.kernels.errors import InputError, SwarmsplatError
    from swarmsplat.registration.pair import make_registrar

    learned = (("xfeat", "xfeat", {}), ("lightglue-disk", "lightglue", dict(features="disk", max_keypoints=1024)),
               ("mast3r", "mast3r", dict(checkpoint=os.environ.get("SWARMSPLAT_MAST3R_CHECKPOINT"))))
    unknown = [n for n in names if not n.startswith("classical") and n not in [r for r, _, _ in learned]]
    if unknown:
        raise InputError(f"fig5: unknown backend rows {unknown}; choose classical, classical-orb or "
                         f"{', '.join(r for r, _, _ in learned)}")
    out = [(n, make_registrar("classical", feature=n.split("-")[1] if "-" in n else "sift"), "") for n in names
           if n.startswith("classical")]
    for row, name, kw in (x for x in learned if x[0] in names):  # without package / weights: one clear line
        try:
            out.append((row, make_registrar(name, **kw), ""))
        except SwarmsplatError as e:
            hint = " (this study reads the path from SWARMSPLAT_MAST3R_CHECKPOINT)" if name == "mast3r" else ""
            out.append((row, None, str(e).splitlines()[0] + hint))
    return out
