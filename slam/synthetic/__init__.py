"""Synthetic multi-agent RGB-D (and monocular) datasets: a procedural indoor world, agent paths that overlap,
ray-cast colour and depth with sensor noise, written in our folder format.

    from swarmsplat.slam.synthetic import GeneratorConfig, generate, generate_world, render
    generate("data/synth", GeneratorConfig.preset("tiny", seed=3))
    world = generate_world(3)
    color, depth = render(world, T_world_cam, camera)   # any pose, noise-free
"""

from .config import PRESETS, GeneratorConfig
from .render import camera_for, cast, render
from .world import World, generate_world
from .writer import agent_poses, dataset_camera, generate

__all__ = ["GeneratorConfig", "PRESETS", "World", "generate_world", "render", "cast", "camera_for",
           "agent_poses", "dataset_camera", "generate"]
