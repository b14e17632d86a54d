"""Place recognition: global descriptors (VLAD default, CosPlace, NetVLAD) and cosine matching (`PlaceDatabase`)."""

from __future__ import annotations

from .base import PAPER_THRESHOLD, PlaceDatabase, PlaceMatch, PlaceRecognizer, l2_normalise

BACKENDS = ("vlad", "cosplace", "netvlad")


def make_recognizer(name: str, *, checkpoint: str | None = None, device: str = "cpu", **options) -> PlaceRecognizer:
    """Build a recogniser by name. 'vlad' with a checkpoint loads that vocabulary (.npz); without, it is untrained
    (call `.fit(images)`). 'cosplace' / 'netvlad' need their published checkpoint."""
    from kernels.errors import InputError

    if name == "vlad":
        from .vlad import VLADRecognizer

        return VLADRecognizer.load(checkpoint) if checkpoint else VLADRecognizer(**options)
    if name == "cosplace":
        from .cosplace import CosPlaceRecognizer

        return CosPlaceRecognizer.from_checkpoint(checkpoint, device=device, **options)
    if name == "netvlad":
        from .netvlad import NetVLADRecognizer

        return NetVLADRecognizer.from_checkpoint(checkpoint, device=device, **options)
    raise InputError(f"unknown place-recognition backend {name!r}; choose one of {BACKENDS}")


__all__ = ["PlaceRecognizer", "PlaceDatabase", "PlaceMatch", "PAPER_THRESHOLD", "l2_normalise", "make_recognizer",
           "BACKENDS"]
