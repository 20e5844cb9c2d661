"""What every part of the scene config shares: the frozen strict model, the error type, path and
rate validators."""

from __future__ import annotations

import math
from fractions import Fraction
from pathlib import Path

from pydantic import BaseModel, ConfigDict


def _inside_scene_dir(v: str, what: str) -> str:
    """A path in the config must be relative and stay inside the scene directory."""
    p = Path(v)
    if p.is_absolute() or ".." in p.parts:
        raise ValueError(f"{v!r}: {what} must lie inside the scene directory (a relative path "
                         "without '..')")
    return v


class ConfigError(ValueError):
    """A scene config problem; ``problems`` holds one ``file: key.path: message`` line each."""

    def __init__(self, problems: list[str]):
        self.problems = problems
        super().__init__("\n".join(problems))


class _Model(BaseModel):
    # NaN and inf are never a meaningful setting: refused everywhere, with the key named.
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


Vec3 = tuple[float, float, float]
Vec2 = tuple[float, float]


def _rate_has_exact_clock(rate_hz: float) -> float:
    if not (rate_hz > 0 and math.isfinite(rate_hz)):
        raise ValueError("rate must be a positive finite number of Hz")
    if Fraction(str(rate_hz)) > 10**9:
        raise ValueError("rate above 1 GHz cannot be sampled on a nanosecond clock")
    return rate_hz
