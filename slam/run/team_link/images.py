"""A keyframe's images on the team link (KeyframeImage), and back on the server.

The server uses two copies of each keyframe: the loop-closure copy (submaps.keep_keyframe_width: place
recognition, registration) and, when it refines the merged map on them (map_refine.views mapping), the
mapping-resolution copy. `link.images`:

  lossless  both copies as the agent holds them, PNG (slam.dense.packed): the server sees its frames bit for bit
  compact   each picture sent once: the colour of the largest copy as JPEG (link.jpeg_quality, full-resolution
            chroma, optimised Huffman tables), the depth of the loop-closure copy in inverse-depth steps (16-bit
            PNG); the server makes the rest: the small colour by area averaging the decoded colour (as the agent
            made its copy), the mapping-resolution depth by interpolating the small one (`upsample_depth`)

Depth in inverse-depth steps: q = round(K / z) with K = 1 / link.depth_step_mm (m), so the step grows as z² like
a structured-light sensor's (0.5 mm at 1 m, 2 mm at 2 m for 0.5 mm; a Kinect's disparity step is about 3 mm at
1 m) and 0 stays "no depth". The refinement weighs depth by 1 - λ_c (0.1) and the overlap cull compares it within
3 cm, so neither notices millimetres; the mapping-resolution depth would cost three times the small one.
"""

from __future__ import annotations

import cv2
import numpy as np

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.slam.dense.frames import RGBD
from swarmsplat.slam.dense.packed import PackedRGBD, pack
from swarmsplat.slam.flocc.swarm.messages import MessageError

# depth forms of a copy (KeyframeImage.depth_form)
FLOAT_BITS, MILLIMETRES, INVERSE, FROM_OTHER = 0, 1, 2, 3


def camera_list(c: PinholeCamera) -> list:
    return [float(c.fx), float(c.fy), float(c.cx), float(c.cy), int(c.width), int(c.height)]


def camera_of(c: list) -> PinholeCamera:
    return PinholeCamera(float(c[0]), float(c[1]), float(c[2]), float(c[3]), int(c[4]), int(c[5]))


def _u8(b: bytes) -> np.ndarray:
    return np.frombuffer(b, np.uint8)


def encode_images(small, map_rgbd, link) -> dict:
    """KeyframeImage's fields (but mid and id) for a keyframe's loop-closure copy `small` and its
    mapping-resolution copy `map_rgbd` (None: not sent), RGBD or PackedRGBD, under `link` (LinkConfig)."""
    if link.images == "lossless":
        out = {"small_camera": camera_list(small.camera), "map_camera": [], "depth_form": []}
        for name, f in (("small", small), ("map", map_rgbd)):
            if f is None:
                continue
            c, d, mm = pack(f).png()
            out.update({f"{name}_color": _u8(c), f"{name}_depth": _u8(d), f"{name}_camera": camera_list(f.camera)})
            out["depth_form"].append(MILLIMETRES if mm else FLOAT_BITS)
        return out
    k = 1000.0 / link.depth_step_mm
    big = small if map_rgbd is None else map_rgbd
    out = {"small_camera": camera_list(small.camera), "map_camera": [] if map_rgbd is None else
           camera_list(map_rgbd.camera), "inverse_depth_k": k, "small_depth": _u8(inverse_depth_png(small.depth, k)),
           "depth_form": [INVERSE] if map_rgbd is None else [INVERSE, FROM_OTHER]}
    out["map_color" if map_rgbd is not None else "small_color"] = _u8(jpeg(big.color, link.jpeg_quality))
    return out


def decode_images(msg) -> tuple[PackedRGBD, PackedRGBD | None]:
    """(loop-closure copy, mapping-resolution copy or None) of a KeyframeImage, packed as the server keeps its
    keyframes. MessageError when the bytes are not the images the message says."""
    small_cam = camera_of(msg.small_camera)
    map_cam = camera_of(msg.map_camera) if msg.map_camera else None
    if msg.depth_form[0] != INVERSE:  # lossless: PNG as the agent packed it
        small = PackedRGBD.from_png(small_cam, msg.small_color.tobytes(), msg.small_depth.tobytes(),
                                    msg.depth_form[0] == MILLIMETRES)
        big = None if map_cam is None else PackedRGBD.from_png(
            map_cam, msg.map_color.tobytes(), msg.map_depth.tobytes(), msg.depth_form[1] == MILLIMETRES)
        return small, big
    depth = _decode(msg.small_depth, "depth", (small_cam.height, small_cam.width), np.uint16)
    depth = np.where(depth > 0, np.float32(msg.inverse_depth_k) / np.maximum(depth, 1).astype(np.float32), 0)
    depth = depth.astype(np.float32)
    if map_cam is None:
        color = _decode(msg.small_color, "colour", (small_cam.height, small_cam.width, 3), np.uint8)
        return PackedRGBD(RGBD(color, depth, small_cam)), None
    color = _decode(msg.map_color, "colour", (map_cam.height, map_cam.width, 3), np.uint8)
    big = RGBD(color, upsample_depth(depth, map_cam.width, map_cam.height), map_cam)
    small_color = cv2.resize(color, (small_cam.width, small_cam.height), interpolation=cv2.INTER_AREA)
    return PackedRGBD(RGBD(small_color, depth, small_cam)), PackedRGBD(big)


def inverse_depth_png(depth: np.ndarray, k: float) -> bytes:
    """16-bit PNG of round(k / depth) (depth in metres, 0 = none stays 0)."""
    z = np.asarray(depth, dtype=np.float64)
    q = np.where(z > 0, np.clip(np.rint(k / np.where(z > 0, z, 1.0)), 1, 65535), 0).astype(np.uint16)
    ok, buf = cv2.imencode(".png", q, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:
        raise RuntimeError(f"PNG encoding failed for a depth image {list(q.shape)}")
    return buf.tobytes()


def jpeg(color: np.ndarray, quality: int) -> bytes:
    """JPEG of an RGB uint8 image [H, W, 3] with full-resolution chroma (4:4:4; slam.dense.packed.pack_lossy says
    why)."""
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(np.ascontiguousarray(color), cv2.COLOR_RGB2BGR),
                           [cv2.IMWRITE_JPEG_QUALITY, int(quality), cv2.IMWRITE_JPEG_OPTIMIZE, 1,
                            cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444])
    if not ok:
        raise RuntimeError(f"JPEG encoding failed for an image {list(color.shape)}")
    return buf.tobytes()


def upsample_depth(depth: np.ndarray, width: int, height: int) -> np.ndarray:
    """A small depth image [h, w] at width x height: each pixel interpolated bilinearly between the small pixels
    around it (their centres where the agent's block means stand, slam.dense.frames) when all of them have depth
    and agree within 2.5 % (a smooth surface), else the nearest small pixel's depth (an edge: no flying pixel
    between two surfaces; a hole stays a hole)."""
    d = np.asarray(depth, np.float32)
    size = (int(width), int(height))
    near = cv2.resize(d, size, interpolation=cv2.INTER_NEAREST)
    lin = cv2.resize(d, size, interpolation=cv2.INTER_LINEAR)
    full = cv2.resize((d > 0).astype(np.float32), size, interpolation=cv2.INTER_LINEAR) > 1 - 1e-6
    smooth = full & (near > 0) & (np.abs(lin - near) <= 0.025 * near)
    return np.where(smooth, lin, near).astype(np.float32)


def _decode(buf: np.ndarray, what: str, shape: tuple, dtype) -> np.ndarray:
    img = cv2.imdecode(np.asarray(buf, np.uint8), cv2.IMREAD_UNCHANGED) if len(buf) else None
    if img is not None and img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    if img is None or img.shape != shape or img.dtype != dtype:
        got = "nothing readable" if img is None else f"{img.dtype} {list(img.shape)}"
        raise MessageError(f"KeyframeImage: the {what} image is not a {np.dtype(dtype)} {list(shape)} image "
                           f"(got {got})")
    return img
