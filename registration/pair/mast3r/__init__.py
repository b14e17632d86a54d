"""MASt3R in torch: architecture (`model`), matching and pose (`matching`), and the pair-registration backend
(`registrar`). Weights come only from a user-given official checkpoint."""

from .model import EncodedImage, Mast3rConfig, Mast3rNet

__all__ = ["Mast3rConfig", "Mast3rNet", "EncodedImage"]
