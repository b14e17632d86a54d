"""Place recognition: global descriptors (thumbnail and BoW need no weights, VLAD, XFeat-VLAD, CosPlace, NetVLAD)
and cosine matching (`PlaceDatabase`)."""

from __future__ import annotations

from .base import PAPER_THRESHOLD, PlaceDatabase, PlaceMatch, PlaceRecognizer, l2_normalise

BACKENDS = ("thumbnail", "bow", "vlad", "xfeat-vlad", "cosplace", "netvlad")
VOCABULARY_BACKENDS = ("bow", "vlad", "xfeat-vlad")  # trained from the robots' own keyframes (`.fit(images)`)


def make_recognizer(name: str, *, checkpoint: str | None = None, device: str = "cpu", **options) -> PlaceRecognizer:
    """Build a recogniser by name. 'thumbnail' needs nothing; 'bow' / 'vlad' / 'xfeat-vlad' with a checkpoint load
    that vocabulary (.npz); without, they are untrained (call `.fit(images)`). 'cosplace' / 'netvlad' need their
    published checkpoint."""
    from swarmsplat.kernels.errors import InputError

    if name == "thumbnail":
        from .thumbnail import ThumbnailRecognizer

        return ThumbnailRecognizer()
    if name in VOCABULARY_BACKENDS:
        from .vlad import _vocabulary_class

        klass = _vocabulary_class(name)
        if not checkpoint:
            return klass(**options)
        rec = klass.load(checkpoint)
        if rec.name != name:
            raise InputError(f"{checkpoint}: is a {rec.name} vocabulary, not {name}")
        return rec
    if name == "cosplace":
        from .cosplace import CosPlaceRecognizer

        return CosPlaceRecognizer.from_checkpoint(checkpoint, device=device, **options)
    if name == "netvlad":
        from .netvlad import NetVLADRecognizer

        return NetVLADRecognizer.from_checkpoint(checkpoint, device=device, **options)
    raise InputError(f"unknown place-recognition backend {name!r}; choose one of {BACKENDS}")


__all__ = ["PlaceRecognizer", "PlaceDatabase", "PlaceMatch", "PAPER_THRESHOLD", "l2_normalise", "make_recognizer",
           "BACKENDS", "VOCABULARY_BACKENDS"]
