"""A simulated image source: a pluggable ``render(displacement_mm) -> 2-D array``.

The ultrasound simulator plugs in as ``render``; tests use :func:`speckle_render`.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from app.devices.imaging import ImageFrame, ImageSource


class SimulatedImageSource(ImageSource):
    """Calls ``render(displacement_mm())`` for each frame."""

    name = "simulated images"

    def __init__(self, render: Callable[[float], np.ndarray], displacement_mm: Callable[[], float]):
        self.render = render
        self.displacement_mm = displacement_mm

    def frame(self) -> ImageFrame:
        d = float(self.displacement_mm())
        img = np.asarray(self.render(d))
        if img.ndim != 2:
            raise ValueError(f"render must return a 2-D array, got shape {img.shape}")
        return ImageFrame(img, {"source": "simulated", "displacement_mm": d})


def speckle_render(shape: tuple[int, int] = (128, 128), spacing_mm: float = 0.2,
                   seed: int = 0) -> Callable[[float], np.ndarray]:
    """A trivial renderer: a fixed speckle texture that moves up by the displacement (uint8)."""
    rows, cols = shape
    rng = np.random.default_rng(seed)
    extra = rows
    texture = (rng.rayleigh(40.0, size=(rows + extra, cols))).clip(0, 255).astype(np.uint8)

    def render(displacement_mm: float) -> np.ndarray:
        shift = int(np.clip(round(displacement_mm / spacing_mm), 0, extra))
        return texture[shift: shift + rows].copy()

    return render
