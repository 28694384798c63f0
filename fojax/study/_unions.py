"""Studies that differ only in their scenario run as members of one union of scenarios
(:func:`fojax.scenarios.union`), so that each controller's runs share one compiled
program: :func:`plan_unions` decides, :func:`stored_alone` keeps a study that an
earlier run stored alone on its own, :func:`agreed` makes process 0's choice every
process's."""

from __future__ import annotations

import json
import os
from pathlib import Path

import jax
import numpy as np

from fojax import scenarios, sharding, simulator
from fojax.controllers import gains_io
from fojax.settings import Settings
from fojax.settings import read as read_settings
from fojax.study._declaration import Study, UnionMember, scenario_of, stored_differences

__all__ = ["agreed", "plan_unions", "stored_alone", "union_enabled", "union_key"]


def union_enabled(settings: Settings | None = None) -> bool:
    """Whether studies that differ only in their scenario and horizon run as members of
    one union of scenarios (``FOJAX_UNION``, default 1; 0: each study on its own
    scenario, one compiled program per study and controller); ``settings``: default
    read now (:func:`fojax.settings.read`)."""
    return (settings or read_settings()).union


def union_key(study: Study):
    """What studies must share (all but the scenario, horizon, draws, seed and keep)
    to run as members of one union with one program per controller."""
    gains = {name: gains_io.gains_to_dict(g) for name, g in study.gains.items()}
    band = study.reaching_band
    return (
        tuple(study.controllers),
        study.dt,
        study.save_every,
        study.fractional,
        study.switching,
        study.device_batch,
        study.dtype,
        tuple(band) if isinstance(band, list | tuple) else band,
        study.rotor_speed_limit,
        json.dumps(gains, sort_keys=True, default=str),
    )


def plan_unions(studies: list[Study], settings: Settings | None = None) -> list[UnionMember | None]:
    """For each study, the union it runs in, or None (alone).

    Studies with the same settings but their scenario and horizon (:func:`union_key`)
    and at least two different scenarios run as members of the union of their
    scenarios (each with its own horizon), so that a controller's runs share one
    compiled program: the simulation runs the union's (longest) horizon and the
    controllers are made for it (their fractional memory spans it), each draw is
    recorded up to its own scenario's horizon, so its metrics and snapshots are those
    of its scenario alone (bit for bit in float64 when the controller does not depend
    on the horizon). Off with ``FOJAX_UNION=0`` (:func:`union_enabled`).
    """
    plans: list[UnionMember | None] = [None] * len(studies)
    if not union_enabled(settings):
        return plans
    groups: dict = {}
    for index, study in enumerate(studies):
        try:
            key = union_key(study)
            hash(key)
        except (TypeError, ValueError):
            continue
        groups.setdefault(key, []).append(index)
    for indices in groups.values():
        members = [scenario_of(studies[i]) for i in indices]
        distinct = list(dict.fromkeys(members))
        if len(distinct) < 2:
            continue
        try:
            bank = scenarios.union(*distinct)
            study = studies[indices[0]]
            simulator.SimulationConfig(
                dt=study.dt, horizon=bank.horizon, save_every=study.save_every
            )
        except ValueError:  # scenarios that cannot share a program
            continue
        for index, member in zip(indices, members, strict=True):
            plans[index] = UnionMember(bank, distinct.index(member))
    return plans


def stored_alone(study: Study, out: str | os.PathLike) -> bool:
    """Whether ``out/chunks`` holds draws of this study run alone (an earlier run
    without the union, which it then continues)."""
    stored = stored_differences(study, out) if (Path(out) / "chunks").is_dir() else []
    return any(differences == [] for _, differences in stored)


def agreed(unions: list[UnionMember | None]) -> list[UnionMember | None]:
    """Process 0's choice of which studies run alone (it alone may see the stores)."""
    if jax.process_count() == 1:
        return unions
    from jax.experimental import multihost_utils

    sharding.barrier("unions")
    alone = np.asarray([u is None for u in unions], np.int32)
    alone = np.asarray(multihost_utils.broadcast_one_to_all(alone))
    return [None if alone[i] else u for i, u in enumerate(unions)]
