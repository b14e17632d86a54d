"""The team server's place descriptors (server.descriptor) and its XFeat keyframe encoder (used by
server.coarse 'learned' and by descriptor 'xfeat-vlad'): what slam.dense.team.server.Server describes each received keyframe
with before it looks for inter-agent candidates."""

from __future__ import annotations

import numpy as np

from swarmsplat.kernels.errors import InputError

from swarmsplat.slam.config import ServerConfig
from swarmsplat.slam.dense.submaps import Keyframe


def make_recognizer_and_encoder(cfg: ServerConfig):
    """(recognizer or None for the agents' own descriptors, slam.dense.loops.learned_coarse.KeyframeEncoder or None)."""
    recognizer = encoder = None
    if cfg.descriptor != "agent":
        from swarmsplat.registration.place_recognition import GENERIC, make_recognizer

        if not cfg.vocabulary and cfg.descriptor != "xfeat-vlad":
            raise InputError(f"server.descriptor {cfg.descriptor!r} needs server.vocabulary (a .npz file)")
        if cfg.vocabulary == "train" and cfg.descriptor != "xfeat-vlad":
            raise InputError(f"server.vocabulary 'train' is for descriptor xfeat-vlad, not {cfg.descriptor!r}")
        checkpoint = {None: GENERIC, "train": None}.get(cfg.vocabulary, cfg.vocabulary)
        recognizer = make_recognizer(cfg.descriptor, checkpoint=checkpoint)
    if cfg.coarse == "learned" or cfg.descriptor == "xfeat-vlad":
        from swarmsplat.slam.dense.loops.learned_coarse import KeyframeEncoder

        encoder = KeyframeEncoder(width=cfg.coarse_width)
    return recognizer, encoder


def coarse_view(kf: Keyframe):
    """The keyframe view the learned coarse start encodes: the mapping-resolution copy while the keyframe has it
    (the encoder downsamples it to server.coarse_width), else the loop-closure copy."""
    return kf.map_rgbd if kf.map_rgbd is not None else kf.small


def describe_keyframe(server, a: int, kf: Keyframe) -> None:
    """Agent a's keyframe into server.descriptors[(a, kf.id)], and into the encoder's cache when the server has
    one (encoded now, while the keyframe still holds its mapping-resolution view). xfeat-vlad comes from that
    encoding; with vocabulary 'train' the first `vocabulary_keyframes` keyframes train it (k-means on their XFeat
    descriptors) and are described then (server._untrained holds them until then)."""
    cfg, rec, enc = server.cfg, server.recognizer, server.encoder
    if enc is not None:
        enc.depth_max = server.slots[a].agent.cfg.image.max_depth
        enc.encode((a, kf.id), coarse_view(kf))
    if rec is None:
        server.descriptors[a, kf.id] = kf.descriptor
        return
    if cfg.descriptor != "xfeat-vlad":
        server.descriptors[a, kf.id] = rec.describe(kf.small.color)
        return
    if rec.trained:
        server.descriptors[a, kf.id] = rec.describe_encoding(enc.cache[a, kf.id])
        return
    server._untrained.append((a, kf.id))
    if len(server._untrained) >= cfg.vocabulary_keyframes:
        parts = [np.asarray(enc.cache[k].arrays["desc"], np.float32) for k in server._untrained]
        if sum(len(p) for p in parts) >= rec.n_clusters:
            rec.fit_local(parts)
            for k in server._untrained:
                server.descriptors[k] = rec.describe_encoding(enc.cache[k])
            server._untrained = []
