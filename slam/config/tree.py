"""The one config tree every command reads: the agent pipeline's sections at the top level (as in every existing
YAML file), then `server` (the GRAND-SLAM team server), `team` (a team run), `swarm` (FLOCC-SLAM), `pairs` (the
front-end over a dataset's keyframe pairs), `demo`, `checkpoint` and `runtime` (offline or real time).

    cfg = SlamConfig.from_yaml("my.yaml")                    # defaults, then the file
    cfg = SlamConfig.from_yaml("my.yaml", preset="demo")     # configs/demo.yaml, then the file
    cfg = SlamConfig.preset("demo-tiny").override({"mapping": {"iterations": 5}})

Loading validates; errors are one line naming the file and the field (slam.config.load). `to_yaml` is what every
run writes as config.yaml next to its results.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, Field, model_validator

from .agent import (ExposureConfig, ImageConfig, KernelsConfig, KeyframeConfig, LoopClosureConfig, MapRefineConfig, MappingConfig,
                    SubmapConfig, TrackingConfig, _Section)
from .link import LinkConfig
from .load import deep_merge, preset_path, read_yaml, validate
from .runtime import RuntimeConfig
from .server import ServerConfig
from .swarm import PairsConfig, SwarmConfig


class TeamConfig(_Section):
    """A GRAND-SLAM team run (`swarmsplat run` on a multi-agent dataset or with --split, `swarmsplat demo`)."""

    stride: int = Field(1, ge=1, description="use every stride-th input frame of each agent")
    render_views: int = Field(8, ge=0, description="keyframes per agent rendered from the merged map for PSNR / "
                                                   "SSIM / depth L1 (0 = all)")


class DemoConfig(_Section):
    """`swarmsplat demo`: the generated dataset it runs on."""

    dataset: Literal["default", "tiny"] = Field("default", description="generator preset (slam.synthetic): "
                                                "'default' 3 agents x 120 frames, 'tiny' 2 agents x 10 frames")
    seed: int | None = Field(None, ge=0, description="generator seed; null: the generator preset's")


class CheckpointConfig(_Section):
    """What `swarmsplat run` keeps on disk while it runs (progress/ in the output folder, docs/robustness.md): the
    pose journal is always written; checkpoints are what `--resume` continues from."""

    every_submaps: int = Field(1, ge=0, description="write a checkpoint of the agent's whole state (submaps, "
                               "keyframes, pose graph, tracker) each time this many submaps have been finished, "
                               "and once after the last frame (0 = never; --resume then starts over). A finished "
                               "submap is frozen, so this bounds both the cost (one write per submap, tens of MB on "
                               "a 320-pixel run) and the work a kill can lose (the frames of one submap)")


class SlamConfig(_Section):
    image: ImageConfig = ImageConfig()
    tracking: TrackingConfig = TrackingConfig()
    keyframes: KeyframeConfig = KeyframeConfig()
    mapping: MappingConfig = MappingConfig()
    map_refine: MapRefineConfig = MapRefineConfig()
    exposure: ExposureConfig = ExposureConfig()
    submaps: SubmapConfig = SubmapConfig()
    loop_closure: LoopClosureConfig = LoopClosureConfig()
    kernels: KernelsConfig = KernelsConfig()
    max_frames: int = Field(0, ge=0, description="process at most this many frames per agent (0 = all)")
    server: ServerConfig = ServerConfig()
    team: TeamConfig = TeamConfig()
    swarm: SwarmConfig = SwarmConfig()
    pairs: PairsConfig = PairsConfig()
    demo: DemoConfig = DemoConfig()
    checkpoint: CheckpointConfig = CheckpointConfig()
    link: LinkConfig = LinkConfig()
    runtime: RuntimeConfig = RuntimeConfig()

    @model_validator(mode="after")
    def _check(self):
        if self.image.min_depth >= self.image.max_depth:
            raise ValueError(f"expected image.min_depth below image.max_depth, got {self.image.min_depth} and "
                             f"{self.image.max_depth}")
        return self

    # ---- YAML -------------------------------------------------------------------------------------------------

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.model_dump(mode="json"), sort_keys=False)

    def override(self, updates: dict[str, Any], where: str = "override") -> "SlamConfig":
        """A new config with nested `updates` merged in (validated; an error line starts with `where`)."""
        return validate(SlamConfig, deep_merge(self.model_dump(mode="json"), updates), where)

    @classmethod
    def preset(cls, name: str) -> "SlamConfig":
        """The preset `configs/<name>.yaml` (slam.config.load.preset_names lists them)."""
        return cls.from_yaml(preset=name)

    @classmethod
    def from_yaml(cls, path: str | Path | None = None, overrides: dict[str, Any] | None = None, *,
                  preset: str | None = None) -> "SlamConfig":
        """Defaults, then the preset (if named), then the YAML file (if given), then `overrides`; raises
        InputError naming the file and the bad field."""
        data: dict[str, Any] = {}
        where = "config"
        if preset is not None:
            where = str(preset_path(preset))
            data = read_yaml(where)
            validate(SlamConfig, data, where)
        if path is not None:
            where = str(path)
            data = deep_merge(data, read_yaml(path))
        cfg = validate(SlamConfig, data, where)
        return cfg.override(overrides) if overrides else cfg


def with_section(config: SlamConfig | BaseModel | None, section: str, options: dict[str, Any],
                 where: str | None = None) -> SlamConfig:
    """The tree `config` (None: the defaults; a lone section model takes its place in them) with `options`
    overriding its `section` (validated; errors start with `where`, default "<section> options")."""
    if config is not None and not isinstance(config, SlamConfig):
        config = SlamConfig().model_copy(update={section: config})
    cfg = config or SlamConfig()
    return cfg.override({section: options}, where=where or f"{section} options") if options else cfg
