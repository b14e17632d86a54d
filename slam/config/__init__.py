"""One validated config tree for every command: the agent pipeline's sections, the team server's, a team run's,
the swarm's, the pairs command's and the demo's (slam.config.tree.SlamConfig); presets are YAML files in configs/."""

from .agent import (ExposureConfig, ImageConfig, KernelsConfig, KeyframeConfig, LoopClosureConfig, MapRefineConfig, MappingConfig,
                    SubmapConfig, TrackingConfig)
from .load import preset_names
from .runtime import RuntimeConfig
from .server import ServerConfig
from .swarm import PairsConfig, SwarmConfig
from .tree import CheckpointConfig, DemoConfig, SlamConfig, TeamConfig, with_section

__all__ = ["CheckpointConfig", "DemoConfig", "ExposureConfig", "ImageConfig", "KernelsConfig", "KeyframeConfig", "LoopClosureConfig", "MapRefineConfig",
           "MappingConfig", "PairsConfig", "RuntimeConfig", "ServerConfig", "SlamConfig", "SubmapConfig", "SwarmConfig", "TeamConfig",
           "TrackingConfig", "preset_names", "with_section"]
