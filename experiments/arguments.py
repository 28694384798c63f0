"""Argument types shared by the ``fojax`` subcommands: checked before anything compiles."""

from __future__ import annotations

import argparse
import math

__all__ = ["nonnegative_float", "nonnegative_int", "positive_float", "positive_int"]


def _integer(text: str, minimum: int, description: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {description}, got {text!r}") from None
    if value < minimum:
        raise argparse.ArgumentTypeError(f"expected {description}, got {value}")
    return value


def _real(text: str, allow_zero: bool, description: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value) or value < 0 or (value == 0 and not allow_zero):
        raise argparse.ArgumentTypeError(f"expected {description}, got {text}")
    return value


def positive_int(text: str) -> int:
    """An integer >= 1."""
    return _integer(text, 1, "a positive integer")


def nonnegative_int(text: str) -> int:
    """An integer >= 0."""
    return _integer(text, 0, "an integer >= 0")


def positive_float(text: str) -> float:
    """A finite number > 0."""
    return _real(text, False, "a finite number > 0")


def nonnegative_float(text: str) -> float:
    """A finite number >= 0."""
    return _real(text, True, "a finite number >= 0")
