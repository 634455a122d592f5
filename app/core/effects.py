"""The physical effects a model may add to the paper's baseline (ids from the
CLI contract). Each relaxes one baseline assumption."""

from __future__ import annotations

EFFECT_IDS = ("hyperelastic", "viscoelastic", "sliding-bottom", "probe-slip", "compressibility", "inclusion")

# ids whose implementation has landed; the model check (issue 5) fills the rest
_AVAILABLE: tuple[str, ...] = ()


def available() -> tuple[str, ...]:
    return _AVAILABLE
