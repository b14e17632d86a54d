"""Which keyframe images the server's map refinement fits (config map_refine.views): a team keeps each keyframe's
mapping-resolution images after its submap is retired when refinement is on with views "mapping", and drops them
otherwise; single agents always drop them."""

import numpy as np

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.dense.frames import RGBD
from swarmsplat.slam.dense.gaussian_map import GaussianMap
from swarmsplat.slam.dense.submaps import Keyframe, start_submap
from swarmsplat.slam.run.team import Team


def _keyframe(i: int, submap: int) -> Keyframe:
    cam = PinholeCamera(40.0, 40.0, 15.5, 11.5, 32, 24)
    f = RGBD(np.zeros((24, 32, 3), np.uint8), np.ones((24, 32), np.float32), cam)
    return Keyframe(i, i, float(i), submap, np.eye(4), f, f.resized(16))


def test_start_submap_drops_or_keeps_the_mapping_images():
    for keep in (False, True):
        gmap = GaussianMap()
        gmap.new_submap(np.eye(4))
        kfs = [_keyframe(0, 0), _keyframe(1, 0)]
        start_submap(gmap, np.eye(4), kfs, keep_images=keep)
        assert len(gmap.submaps) == 2
        assert all((k.map_rgbd is not None) == keep for k in kfs)
        assert all(k.small is not None for k in kfs)


def test_team_keeps_images_only_for_mapping_resolution_refinement():
    cam = PinholeCamera(40.0, 40.0, 15.5, 11.5, 32, 24)
    cases = [({}, True), ({"map_refine": {"views": "small"}}, False),
             ({"map_refine": {"iterations_per_keyframe": 0}}, False), ({"map_refine": {"max_iterations": 0}}, False)]
    for override, want in cases:
        team = Team([cam, cam], ["a", "b"], SlamConfig().override(override))
        assert [ag.keep_keyframe_images for ag in team.agents] == [want, want], override
