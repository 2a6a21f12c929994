"""`Boxer2DConfig`: every architecture setting of the image-plane detector, in one place."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any


@dataclass(frozen=True)
class Boxer2DConfig:
    """Architecture of `Boxer2D` (the weights file stores it as JSON).

    Input images are `image_size = (W, H)` pixels with RGB + depth channels; they are padded
    at the bottom to `input_size` (a multiple of the backbone's stride 4), the frame that
    normalised boxes refer to.
    """

    classes: tuple[str, ...]
    image_size: tuple[int, int] = (120, 71)
    input_size: tuple[int, int] = (120, 72)
    depth_range: float = 70.0          # metres; the depth channel is divided by it
    c1: int = 32                       # backbone channels at stride 2
    c2: int = 64                       # ... at strides 4 and 8
    d_model: int = 64
    n_heads: int = 4
    d_ffn: int = 128
    n_encoder: int = 1
    n_decoder: int = 3
    n_queries: int = 30                # top-scoring proposals per image -> decoder queries
    anchor_px: float = 16.0            # side of every encoder token's reference window

    def __post_init__(self) -> None:
        if self.input_size[0] % 8 or self.input_size[1] % 8:
            raise ValueError(f"input_size must be multiples of 8, got {self.input_size}")
        if self.input_size[0] < self.image_size[0] or self.input_size[1] < self.image_size[1]:
            raise ValueError(f"input_size {self.input_size} is smaller than image_size "
                             f"{self.image_size}")
        if self.d_model % 4 or self.d_model % self.n_heads:
            raise ValueError(f"d_model must be a multiple of 4 and of n_heads "
                             f"{self.n_heads}, got {self.d_model}")

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict (tuples as lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Boxer2DConfig:
        """Inverse of `to_dict`; unknown keys are an error."""
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"unknown Boxer2DConfig keys: {sorted(unknown)}")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()})
