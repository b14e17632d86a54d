"""A keyframe's images on the team link (slam.run.team_link.images): lossless copies come back bit for bit;
compact ones send each picture once and the server makes the rest as the agent made its copies, with depth
within half an inverse-depth step; bytes that are not the images a message says are refused with a clear error."""

from __future__ import annotations

import numpy as np
import pytest

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.dense.frames import RGBD
from swarmsplat.slam.flocc.swarm.messages import MessageError
from swarmsplat.slam.run.team_link import messages as L
from swarmsplat.slam.run.team_link.images import decode_images, encode_images


def frame(w: int = 64, h: int = 48) -> RGBD:
    v, u = np.mgrid[0:h, 0:w]
    color = np.stack([(4 * u) % 256, (5 * v) % 256, (u + v) % 256], -1).astype(np.uint8)  # smooth ramps
    depth = (0.4 + 3.5 * u / w + 0.5 * v / h).astype(np.float32)
    depth[:6, :6] = 0.0  # no depth there
    return RGBD(color, depth, PinholeCamera(60, 60, (w - 1) / 2, (h - 1) / 2, w, h))


def through_the_link(small, big, link) -> tuple:
    fields = encode_images(small, big, link)
    _, msg = L.LINK.decode(L.LINK.encode(L.KeyframeImage(mid=1, id=4, **fields), 1, 1))
    return msg, decode_images(msg)


def test_lossless_copies_come_back_bit_for_bit():
    f = frame()
    small = f.resized(32)
    _, (s, b) = through_the_link(small, f, SlamConfig().link.model_copy(update={"images": "lossless"}))
    assert np.array_equal(s.color, small.color) and np.array_equal(s.depth, small.depth)
    assert np.array_equal(b.color, f.color) and np.array_equal(b.depth, f.depth)


@pytest.mark.parametrize("with_map", [True, False])
def test_compact_images_send_each_picture_once_within_the_stated_steps(with_map):
    f = frame()
    small = f.resized(32)
    link = SlamConfig().link.model_copy(update={"images": "compact", "depth_step_mm": 0.5})
    msg, (s, b) = through_the_link(small, f if with_map else None, link)
    assert len(msg.small_depth) and not len(msg.map_depth)  # one depth, one colour
    assert bool(len(msg.map_color)) == with_map and bool(len(msg.small_color)) != with_map
    z = small.depth
    step = 0.5e-3 * z.astype(np.float64) ** 2  # the inverse-depth step at range z, to first order
    assert np.all((s.depth == 0) == (z == 0))
    assert np.all(np.abs(s.depth - z) <= 0.5 * step * 1.01 + 1e-6)
    assert np.abs(s.color.astype(int) - small.color).mean() < 3  # JPEG at quality 90 (of the larger copy)
    if with_map:
        assert b.camera == f.camera and np.abs(b.color.astype(int) - f.color).mean() < 3
        # the mapping copy's depth: the small one interpolated on the smooth ramp, holes where it has none
        inside = np.repeat(np.repeat(s.depth > 0, 2, 0), 2, 1)
        assert np.all(b.depth[~inside] == 0) and np.all(b.depth[inside] > 0)
        err = np.abs(b.depth - f.depth)[inside]
        assert np.median(err) < 2e-3 and err.max() < 0.06  # a step within a pixel, a block's slope at edges
    else:
        assert b is None


def test_images_that_are_not_what_the_message_says_are_refused():
    f = frame()
    small = f.resized(32)
    link = SlamConfig().link.model_copy(update={"images": "compact"})
    fields = encode_images(small, f, link)
    with pytest.raises(MessageError, match=r"the colour image is not a uint8 \[48, 64, 3\] image"):
        decode_images(L.KeyframeImage(mid=1, id=4, **{**fields, "map_color": fields["map_color"][:40]}))
    with pytest.raises(MessageError, match=r"the depth image is not a uint16 \[24, 32\] image"):
        decode_images(L.KeyframeImage(mid=1, id=4, **{**fields, "small_depth": fields["map_color"]}))
    with pytest.raises(MessageError, match="inverse-depth images need k > 0"):
        L.KeyframeImage(mid=1, id=4, **{**fields, "inverse_depth_k": 0.0}).validate()
    with pytest.raises(MessageError, match="lossless images need every copy's colour and depth"):
        L.KeyframeImage(mid=1, id=4, small_camera=fields["small_camera"], depth_form=[1]).validate()
