"""One validated config tree for every command: the agent pipeline's sections and the team server's."""

from .agent import (ImageConfig, KernelsConfig, KeyframeConfig, LoopClosureConfig, MapRefineConfig, MappingConfig,
                    SlamConfig, SubmapConfig, TrackingConfig)
from .server import ServerConfig

__all__ = ["ImageConfig", "KernelsConfig", "KeyframeConfig", "LoopClosureConfig", "MapRefineConfig", "MappingConfig",
           "ServerConfig", "SlamConfig", "SubmapConfig", "TrackingConfig"]
