"""Checks of settings, in Python before anything is traced: each raises a ``ValueError``
that names the setting, what it must be and what it got."""

from __future__ import annotations

import math

__all__ = ["choice", "integer", "number"]


def number(label: str, value, low: float = 0.0, *, allow_low: bool = False, high=None) -> None:
    """``value`` is a finite number ``> low`` (``>= low`` with ``allow_low``), and
    ``<= high`` where given."""
    inside = isinstance(value, int | float) and not isinstance(value, bool)
    inside = inside and math.isfinite(value) and (value >= low if allow_low else value > low)
    if not inside or (high is not None and value > high):
        bound = f"{'>=' if allow_low else '>'} {low:g}" + (f" and <= {high:g}" if high else "")
        raise ValueError(f"{label} must be a finite number {bound}, got {value!r}")


def integer(label: str, value, low: int = 1) -> None:
    """``value`` is an integer ``>= low`` (not a bool)."""
    if not isinstance(value, int) or isinstance(value, bool) or value < low:
        raise ValueError(f"{label} must be an integer >= {low}, got {value!r}")


def choice(label: str, value, choices) -> None:
    """``value`` is one of ``choices``."""
    if value not in choices:
        raise ValueError(f"{label} must be one of {', '.join(map(str, choices))}, got {value!r}")
