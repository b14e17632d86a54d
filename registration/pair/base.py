"""Image-pair registration with the encode/decode split of FLOCC-SLAM (Fig. 1).

`encode(image)` runs once per keyframe on the robot that owns it; the `Encoding` travels as bytes (its size is
what the robots pay on the link); `register(enc_query, enc_match, camera_query, camera_match)` runs on one robot
and returns the relative pose up to scale and the number of correspondences that the confidence of eq. (1) uses.

Pose convention: `PairResult.R`, `PairResult.t` describe `T_query_match` — the match camera's pose in the query
camera's frame (x_query = R x_match + t), the measurement `T^{alpha,i}_{beta,j} = T_{alpha,i}^-1 T_{beta,j}` of
eq. (3) with alpha = query. `t` is a unit vector: monocular registration has no scale.
"""

from __future__ import annotations

import json
import struct
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

from swarmsplat.kernels import se3
from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import InputError

_MAGIC = b"SSENC1"


@dataclass
class Encoding:
    """What one robot sends for one keyframe: named arrays plus a small JSON-able header.

    backend: the backend that made it (decoding with another backend is refused).
    image_size: (width, height) of the image that was encoded, in pixels.
    arrays: name -> numpy array (keypoints, descriptors, tokens, ...).
    meta: extra JSON-able fields (resize factors, crop offsets, ...).
    """

    backend: str
    image_size: tuple[int, int]
    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    meta: dict = field(default_factory=dict)

    def to_bytes(self) -> bytes:
        """Self-describing binary form: magic, header length, JSON header, then each array's raw bytes."""
        specs, blobs = [], []
        for name, a in self.arrays.items():
            a = np.ascontiguousarray(a)
            specs.append({"name": name, "dtype": a.dtype.str, "shape": list(a.shape)})
            blobs.append(a.tobytes())
        header = json.dumps({"backend": self.backend, "image_size": list(self.image_size), "arrays": specs,
                             "meta": self.meta}, separators=(",", ":")).encode()
        return _MAGIC + struct.pack("<I", len(header)) + header + b"".join(blobs)

    @classmethod
    def from_bytes(cls, data: bytes) -> "Encoding":
        """Inverse of `to_bytes`; malformed or truncated data raises InputError."""
        if not isinstance(data, (bytes, bytearray, memoryview)) or bytes(data[:6]) != _MAGIC or len(data) < 10:
            raise InputError("Encoding.from_bytes: not an encoding (bad magic or too short)")
        data = bytes(data)
        (n,) = struct.unpack("<I", data[6:10])
        try:
            header = json.loads(data[10 : 10 + n])
        except ValueError as e:
            raise InputError(f"Encoding.from_bytes: corrupt header: {e}") from None
        off = 10 + n
        arrays = {}
        try:
            for spec in header["arrays"]:
                dt = np.dtype(spec["dtype"])
                if dt.hasobject:
                    raise ValueError("object arrays are not allowed")
                size = int(np.prod(spec["shape"], dtype=np.int64)) * dt.itemsize
                if off + size > len(data):
                    raise InputError(f"Encoding.from_bytes: truncated data in array {spec['name']!r}")
                arrays[spec["name"]] = np.frombuffer(data, dt, count=size // dt.itemsize if dt.itemsize else 0,
                                                     offset=off).reshape(spec["shape"]).copy()
                off += size
            enc = cls(str(header["backend"]), tuple(int(v) for v in header["image_size"]), arrays,
                      dict(header.get("meta", {})))
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"Encoding.from_bytes: malformed header: {type(e).__name__}: {e}") from None
        if off != len(data):
            raise InputError(f"Encoding.from_bytes: {len(data) - off} trailing bytes")
        return enc

    @property
    def nbytes(self) -> int:
        """Size on the wire in bytes (length of `to_bytes()`)."""
        return len(self.to_bytes())


@dataclass
class PairResult:
    """Outcome of registering one image pair. R, t give T_query_match (t unit norm, no scale).

    n_correspondences: the count eq. (1) divides (per backend: geometrically verified matches for classical
        and learned matchers, reciprocal matches for MASt3R).
    n_matches: putative matches before geometric verification.
    inlier_mask: [n_matches] bool, which putative matches the robust estimator kept.
    points_query / points_match: [n_matches, 2] matched pixel coordinates in each original image.
    success: False when the pair could not be registered; `reason` then says why and R, t are identity / zero.
    """

    R: np.ndarray
    t: np.ndarray
    n_correspondences: int
    n_matches: int
    success: bool
    reason: str = ""
    inlier_mask: np.ndarray | None = None
    points_query: np.ndarray | None = None
    points_match: np.ndarray | None = None
    extras: dict = field(default_factory=dict)

    @property
    def inlier_ratio(self) -> float:
        return float(self.n_correspondences) / self.n_matches if self.n_matches else 0.0

    @property
    def T_query_match(self) -> np.ndarray:
        """[4, 4] with a unit-norm translation (scale it with odometry, FLOCC eq. (6))."""
        return se3.make(self.R, self.t)

    @classmethod
    def failed(cls, reason: str, n_matches: int = 0, n_correspondences: int = 0, **kw) -> "PairResult":
        return cls(np.eye(3), np.zeros(3), int(n_correspondences), int(n_matches), False, reason, **kw)


class PairRegistrar(ABC):
    """A pair-registration backend: `encode` per image, `register` per pair."""

    name: str = "base"

    @abstractmethod
    def encode(self, image: np.ndarray) -> Encoding:
        """RGB uint8 [H, W, 3] -> Encoding. Malformed images raise InputError."""

    @abstractmethod
    def register(self, enc_query: Encoding, enc_match: Encoding, camera_query: PinholeCamera,
                 camera_match: PinholeCamera | None = None) -> PairResult:
        """Relative pose T_query_match up to scale. `camera_match` defaults to `camera_query` (same robot model).

        Cameras describe the images as they were given to `encode` (their width/height must match).
        A pair that cannot be registered gives `success=False` with a reason, never an exception.
        """

    def register_images(self, image_query: np.ndarray, image_match: np.ndarray, camera_query: PinholeCamera,
                        camera_match: PinholeCamera | None = None) -> PairResult:
        """Encode both images and register them (the naive path without caching)."""
        return self.register(self.encode(image_query), self.encode(image_match), camera_query, camera_match)

    def _check_inputs(self, enc_query: Encoding, enc_match: Encoding, camera_query: PinholeCamera,
                      camera_match: PinholeCamera | None) -> PinholeCamera:
        for nm, enc in (("enc_query", enc_query), ("enc_match", enc_match)):
            if not isinstance(enc, Encoding):
                raise InputError(f"{self.name}.register: {nm} must be an Encoding, got {type(enc).__name__}")
            if enc.backend != self.name:
                raise InputError(f"{self.name}.register: {nm} was made by backend {enc.backend!r}, not {self.name!r}")
        camera_match = camera_query if camera_match is None else camera_match
        for nm, cam, enc in (("camera_query", camera_query, enc_query), ("camera_match", camera_match, enc_match)):
            if not isinstance(cam, PinholeCamera):
                raise InputError(f"{self.name}.register: {nm} must be a PinholeCamera, got {type(cam).__name__}")
            if (cam.width, cam.height) != tuple(enc.image_size):
                raise InputError(f"{self.name}.register: {nm} is {cam.width}x{cam.height} but its image was "
                                 f"{enc.image_size[0]}x{enc.image_size[1]}; use camera.scaled(w, h)")
        return camera_match


def import_optional(module: str, install_hint: str):
    """Import an optional package of a learned backend, or raise one BackendError line saying how to install it."""
    import importlib

    from swarmsplat.kernels.errors import BackendError

    try:
        return importlib.import_module(module)
    except ImportError as e:
        raise BackendError(f"{install_hint}: {e}") from None


def pose_from_essential_inverse(R_m_q: np.ndarray, t_m_q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's recoverPose gives x_match = R x_query + t (T_match_query); return (R, t) of T_query_match."""
    R = R_m_q.T
    t = -R_m_q.T @ np.asarray(t_m_q, float).reshape(3)
    n = np.linalg.norm(t)
    return R, (t / n if n > 0 else t)


def rotation_error_deg(R_est: np.ndarray, R_true: np.ndarray) -> float:
    """Geodesic angle between two rotations, degrees."""
    return float(np.rad2deg(se3.rotation_angle(R_est.T @ R_true)))


def direction_error_deg(t_est: np.ndarray, t_true: np.ndarray) -> float:
    """Angle between two translation directions, degrees (NaN when either is zero)."""
    a, b = np.linalg.norm(t_est), np.linalg.norm(t_true)
    if a < 1e-12 or b < 1e-12:
        return float("nan")
    return float(np.rad2deg(np.arccos(np.clip(np.dot(t_est, t_true) / (a * b), -1.0, 1.0))))
