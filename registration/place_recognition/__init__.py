"""Place recognition: global descriptors (thumbnail and BoW need no weights, VLAD, XFeat-VLAD, CosPlace, NetVLAD)
and cosine matching (`PlaceDatabase`)."""

from __future__ import annotations

from .base import PAPER_THRESHOLD, PlaceDatabase, PlaceMatch, PlaceRecognizer, l2_normalise

from pathlib import Path

BACKENDS = ("thumbnail", "bow", "vlad", "xfeat-vlad", "cosplace", "netvlad")
# The vocabulary shipped for xfeat-vlad (checkpoint="generic"): 32 words from generated worlds only
# (swarmsplat.slam.synthetic.vocabulary makes it); measured on real and generated revisits in perf/results/placerec-cpu.md.
GENERIC = "generic"
GENERIC_VOCABULARY = Path(__file__).parent / "vocabularies" / "xfeat-vlad-k32.npz"
VOCABULARY_BACKENDS = ("bow", "vlad", "xfeat-vlad")  # trained from the robots' own keyframes (`.fit(images)`)


def make_recognizer(name: str, *, checkpoint: str | None = None, device: str = "cpu", **options) -> PlaceRecognizer:
    """Build a recogniser by name. 'thumbnail' needs nothing; 'bow' / 'vlad' / 'xfeat-vlad' with a checkpoint load
    that vocabulary (.npz); without, they are untrained (call `.fit(images)`); 'xfeat-vlad' with checkpoint
    "generic" loads the vocabulary shipped with the package. 'cosplace' / 'netvlad' need their published
    checkpoint."""
    from swarmsplat.kernels.errors import InputError

    if name == "thumbnail":
        from .thumbnail import ThumbnailRecognizer

        return ThumbnailRecognizer()
    if name in VOCABULARY_BACKENDS:
        from .vlad import _vocabulary_class

        klass = _vocabulary_class(name)
        if checkpoint == GENERIC:
            if name != "xfeat-vlad":
                raise InputError(f"no generic vocabulary ships for {name!r}; give a .npz file (only xfeat-vlad has one)")
            checkpoint = str(GENERIC_VOCABULARY)
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
           "BACKENDS", "VOCABULARY_BACKENDS", "GENERIC", "GENERIC_VOCABULARY"]
