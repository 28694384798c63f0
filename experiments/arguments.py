"""Argument types shared by the ``fojax`` subcommands: checked before anything compiles."""

from __future__ import annotations

import argparse
import math
import os
import sys

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


def scenario_ids(text: str) -> tuple[int, ...]:
    """Comma-separated scenario ids, e.g. ``1,3``: sorted, without repeats."""
    from fojax import scenarios

    try:
        ids = tuple(sorted({int(part) for part in text.split(",") if part.strip()}))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected scenario ids like 1,2,3, got {text!r}"
        ) from None
    bad = [i for i in ids if i not in scenarios.SCENARIO_IDS]
    if not ids or bad:
        raise argparse.ArgumentTypeError(
            f"scenarios must be among {scenarios.SCENARIO_IDS}, got {text!r}"
        )
    return ids


def use_host_devices(requested: int | None = None) -> int | None:
    """Ask XLA for one CPU device per core (or ``requested``) unless JAX has started.

    XLA's CPU backend runs one program on one device; with several host devices
    :mod:`fojax.sharding` splits the draws over the cores (about 1.5-1.8x the
    throughput of one device on 2 cores, ``docs/performance.md``). Only the CPU
    platform is affected: on a GPU machine the GPUs stay the default devices. Returns
    the count asked for, or None when JAX had already started (then nothing changes)
    or ``XLA_FLAGS`` already sets it.
    """
    if "jax" in sys.modules:
        return None
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_force_host_platform_device_count" in flags:
        return None
    count = requested or os.cpu_count() or 1
    os.environ["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={count}".strip()
    return count
