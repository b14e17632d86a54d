"""Typed settings of the synthetic generator, with named presets.

`GeneratorConfig.preset("tiny")` is what the tests use (2 agents, 10 frames, 160x120, a few seconds);
`"default"` is the demo dataset (3 agents, 120 frames, 320x240); `"twin"` two copies of one room in two
buildings, seen by different agents (the repeated-structure negative). Every field is written into `dataset.yaml`
under `generator:`, so a dataset records exactly how it was made.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_serializer, model_validator

from swarmsplat.kernels.errors import InputError

MAX_AGENTS = 6


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class WorldConfig(_Strict):
    """Procedural indoor world: a grid of rooms joined by openings, furnished at random."""

    rooms_x: int = Field(2, ge=1, le=4)
    rooms_y: int = Field(2, ge=1, le=4)
    room_size_m: tuple[float, float] = (3.6, 4.8)  # range of each room's width and depth
    height_m: tuple[float, float] = (2.6, 3.0)  # range of the ceiling height (one per world)
    furniture_per_room: tuple[int, int] = (4, 7)
    # A second copy of the building stands beside the first, out of sight of it (slam.synthetic.world): "room"
    # repeats room A only (geometry, furniture and textures; the other rooms are furnished and painted anew),
    # "building" repeats every room. Agent k walks slot k // 2's path in copy k % 2, so agents 0 and 1 see the
    # two copies of room A from the same places. "none": one building.
    twin: Literal["none", "room", "building"] = "none"

    @model_serializer(mode="wrap")
    def _dump(self, handler):
        # Without a twin the field is left out, so datasets written before it existed still match their settings
        # (slam.run.demo reuses a dataset whose dataset.yaml records identical generator settings).
        out = handler(self)
        if self.twin == "none":
            out.pop("twin", None)
        return out

    @model_validator(mode="after")
    def _check(self):
        if self.rooms_x * self.rooms_y < 2:
            raise ValueError("the world needs at least 2 rooms (rooms_x * rooms_y >= 2)")
        lo, hi = self.room_size_m
        if not 3.5 <= lo <= hi <= 12.0:
            raise ValueError("room_size_m must satisfy 3.5 <= min <= max <= 12")
        if not 2.2 <= self.height_m[0] <= self.height_m[1] <= 5.0:
            raise ValueError("height_m must satisfy 2.2 <= min <= max <= 5")
        if not 0 <= self.furniture_per_room[0] <= self.furniture_per_room[1] <= 20:
            raise ValueError("furniture_per_room must satisfy 0 <= min <= max <= 20")
        return self


class MotionConfig(_Strict):
    """Per-frame motion limits and how much of its loop an agent repeats (the revisit)."""

    max_step_m: float = Field(0.045, gt=0.0, le=1.0)  # translation per frame, at most
    max_rot_deg: float = Field(2.8, gt=0.0, le=30.0)  # rotation per frame, at most
    loop_turns: float = Field(1.3, gt=0.0, le=5.0)  # > 1 means the start of the loop is seen again


class DepthNoiseConfig(_Strict):
    """Structured-light-like depth: axial noise growing with range, disparity quantisation, holes."""

    enabled: bool = True
    sigma_m: tuple[float, float, float] = (0.0012, 0.0019, 0.4)  # sigma(z) = a + b (z - c)^2 (Nguyen et al. 2012)
    disparity_fb: float = Field(40.0, gt=0.0)  # focal length x baseline, pixel*metre (Kinect-like)
    disparity_step: float = Field(1.0 / 16.0, ge=0.0)  # disparity quantisation in pixels, 0 = none
    min_m: float = Field(0.3, ge=0.0)
    max_m: float = Field(7.0, gt=0.0)
    grazing_cos: float = Field(0.12, ge=0.0, lt=1.0)  # holes where |cos(incidence)| is below this
    edge_dropout: float = Field(0.5, ge=0.0, le=1.0)  # probability of a hole on a depth discontinuity
    blob_holes: float = Field(0.01, ge=0.0, le=0.5)  # fraction of the image lost to clustered holes


class ColorNoiseConfig(_Strict):
    enabled: bool = True
    sigma: float = Field(2.0, ge=0.0, le=50.0)  # per-channel Gaussian noise, 8-bit units


class MonoConfig(_Strict):
    """Metric odometry of the monocular variant: noisy increments, a yaw bias and an optional scale error."""

    trans_noise: float = Field(0.02, ge=0.0, le=1.0)  # sigma of translation error per metre travelled, as a fraction
    rot_noise_deg_per_m: float = Field(1.0, ge=0.0, le=90.0)  # sigma of rotation error per metre travelled
    yaw_bias_deg_per_m: float = Field(1.0, ge=-90.0, le=90.0)  # systematic heading drift (gyro bias)
    scale: float = Field(1.0, gt=0.0, le=10.0)  # odometry translation = scale * true translation


MAX_SUPERSAMPLE = 8  # rays per pixel side: 64 rays per pixel at most (render.check_supersample too)


class GeneratorConfig(_Strict):
    name: str = "synthetic"
    seed: int = Field(0, ge=0, lt=2**31)
    agents: int = Field(3, ge=1, le=MAX_AGENTS)
    frames: int = Field(120, ge=1, le=100_000)
    width: int = Field(320, ge=16, le=4096)
    height: int = Field(240, ge=16, le=4096)
    fps: float = Field(15.0, gt=0.0, le=1000.0)
    hfov_deg: float = Field(62.8, gt=10.0, lt=170.0)  # a Kinect-like field of view (fx = 525 at 640 px)
    # Rays per pixel side: colour is the mean of supersample^2 rays over the pixel's area, depth the pixel-centre
    # ray's (slam.synthetic.render). 1 = one ray through the pixel centre, which aliases every edge and texture.
    supersample: int = Field(2, ge=1, le=MAX_SUPERSAMPLE)
    depth_scale: float = Field(5000.0, gt=0.0)  # uint16 value per metre, as TUM RGB-D
    mono: bool = False
    # Version of the agent-slot layout of trajectories.py. Only the current one is generated; it is part of
    # dataset.yaml's `generator:` so a cached dataset made with other paths no longer matches (demo.ensure_dataset).
    trajectory_layout: Literal[2] = 2
    world: WorldConfig = WorldConfig()
    motion: MotionConfig = MotionConfig()
    depth_noise: DepthNoiseConfig = DepthNoiseConfig()
    color_noise: ColorNoiseConfig = ColorNoiseConfig()
    odometry: MonoConfig = MonoConfig()

    @property
    def kind(self) -> Literal["rgbd", "mono"]:
        return "mono" if self.mono else "rgbd"

    @classmethod
    def preset(cls, name: str, **overrides) -> "GeneratorConfig":
        """A named preset with top-level fields overridden (None values are ignored)."""
        if name not in PRESETS:
            raise InputError(f"unknown generator preset {name!r}; choose one of {', '.join(sorted(PRESETS))}")
        fields = dict(PRESETS[name])
        fields.update({k: v for k, v in overrides.items() if v is not None})
        return cls.build(**fields)

    @classmethod
    def build(cls, **fields) -> "GeneratorConfig":
        """Construct and validate; a bad value raises InputError naming the field."""
        try:
            return cls(**fields)
        except ValidationError as e:
            err = e.errors()[0]
            where = ".".join(str(p) for p in err["loc"]) or "config"
            raise InputError(f"generator setting '{where}': {err['msg']}") from None


PRESETS: dict[str, dict] = {
    # Tests: two agents, a few frames, small images; generates in a few seconds.
    "tiny": dict(name="synthetic_tiny", agents=2, frames=10, width=160, height=120),
    # The demo dataset: three agents, small enough for the whole demo to run in minutes on 2 cores.
    "default": dict(name="synthetic", agents=3, frames=120, width=320, height=240),
    # Longer sequences with all six agents, for benchmarks on bigger machines.
    "large": dict(name="synthetic_large", agents=6, frames=400, width=640, height=480,
                  world=WorldConfig(rooms_x=3, rooms_y=2), motion=MotionConfig(loop_turns=2.0)),
    # Twin rooms: the default building and a copy of it whose room A is the same room (WorldConfig.twin);
    # agents 0 and 2 in copy 1, 1 and 3 in copy 2. Agents of different copies must not join (decision 0012).
    "twin": dict(name="synthetic_twin", agents=4, frames=120, width=320, height=240, world=WorldConfig(twin="room")),
}
