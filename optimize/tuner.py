"""Gradient-based gain tuning on optax, with checkpoints and exact resume.

Each step ``k = 0 ... steps - 1``:

1. draws: minibatch ``k`` of the tuning stream (:meth:`TuningProblem.minibatch_keys`:
   fresh draws every step, disjoint from the held-out ones);
2. switching: ``tanh(S / (scale_k w))`` with ``scale_k`` geometric from
   ``anneal_start`` to ``anneal_end`` (the evaluation width of ``sat`` at 1);
3. the objective (mean or CVaR, :mod:`optimize.cost`) and its gradient by reverse
   mode through the whole horizon (the rollout rematerialises each block of
   ``save_every`` steps);
4. ``clip_by_global_norm(clip_norm)`` then Adam with a cosine-decayed learning rate
   (from ``learning_rate`` to ``final_learning_rate`` times it), on the unconstrained
   parameters of :mod:`optimize.params` (so every iterate is feasible).

Every ``checkpoint_every`` steps (and at the end, and on Ctrl-C) the parameters,
the optimiser state, the step, the history and the counters are written to
``DIR/checkpoint.npz`` atomically (a temporary file, then ``os.replace``). A resumed
run reloads them and continues with the same minibatches and schedules, so it
reproduces the uninterrupted run exactly (same compiled functions, same inputs).
A checkpoint records the run's fingerprint (problem, tuner settings, initial gains);
resuming with any difference is refused with the list of differences. Nothing is
written before every input has been checked.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from fojax.controllers import gains_io
from optimize.problem import ProblemSpec, TuningProblem

__all__ = [
    "CHECKPOINT",
    "HISTORY_COLUMNS",
    "TuneResult",
    "TunerConfig",
    "fingerprint",
    "prepare",
    "tune",
    "width_scale",
]

CHECKPOINT = "checkpoint.npz"
FORMAT = 1
HISTORY_COLUMNS = (
    "step",
    "objective",
    "mean_cost",
    "max_cost",
    "grad_norm",
    "learning_rate",
    "width_scale",
    "diverged",
    "bad_gradients",
    "draw_steps",
    "wall_time_s",
)


@dataclasses.dataclass(frozen=True)
class TunerConfig:
    """Settings of the gradient tuner (validated on construction).

    steps: optimisation steps (>= 1). learning_rate: Adam's initial step (> 0), in the
    unconstrained parameters (about a relative change for log-mapped gains).
    final_learning_rate: fraction of it reached at the last step (cosine decay, in
    ``[0, 1]``). clip_norm: global gradient-norm clip (> 0). anneal_start,
    anneal_end: boundary-layer scale of the first and last step (> 0).
    checkpoint_every: steps between checkpoints (>= 1).
    """

    steps: int = 100
    learning_rate: float = 0.05
    final_learning_rate: float = 0.1
    clip_norm: float = 1.0
    anneal_start: float = 4.0
    anneal_end: float = 1.0
    checkpoint_every: int = 10

    def __post_init__(self) -> None:
        for label in ("steps", "checkpoint_every"):
            value = getattr(self, label)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"{label} must be a positive integer, got {value!r}")
        for label in ("learning_rate", "clip_norm", "anneal_start", "anneal_end"):
            value = getattr(self, label)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{label} must be a finite number > 0, got {value!r}")
        if not (0 <= self.final_learning_rate <= 1):
            raise ValueError(
                f"final_learning_rate must be in [0, 1], got {self.final_learning_rate!r}"
            )

    def optimizer(self) -> optax.GradientTransformation:
        schedule = optax.cosine_decay_schedule(
            self.learning_rate, max(self.steps - 1, 1), alpha=self.final_learning_rate
        )
        return optax.chain(optax.clip_by_global_norm(self.clip_norm), optax.adam(schedule))

    def learning_rate_at(self, step: int) -> float:
        fraction = min(step, max(self.steps - 1, 1)) / max(self.steps - 1, 1)
        cosine = 0.5 * (1 + math.cos(math.pi * fraction))
        return self.learning_rate * (
            (1 - self.final_learning_rate) * cosine + self.final_learning_rate
        )


def width_scale(config: TunerConfig, step: int) -> float:
    """Boundary-layer scale of step ``step`` (geometric from start to end)."""
    if config.steps == 1:
        return float(config.anneal_end)
    fraction = step / (config.steps - 1)
    return float(config.anneal_start * (config.anneal_end / config.anneal_start) ** fraction)


class TuneResult(NamedTuple):
    """params: final unconstrained parameters. gains: the evaluation gains.
    history: one dict per step (:data:`HISTORY_COLUMNS`). completed: steps done.
    problem: the :class:`TuningProblem`."""

    params: dict
    gains: Any
    history: list
    completed: int
    problem: TuningProblem


def fingerprint(spec: ProblemSpec, config: TunerConfig, init_label: str, init_gains) -> dict:
    """Everything a checkpoint must agree on to be resumed."""
    return {
        "format": FORMAT,
        "problem": spec.as_dict(),
        "tuner": dataclasses.asdict(config),
        "init": init_label,
        "init_gains": gains_io.gains_to_dict(
            type(init_gains)(*(np.asarray(g, np.float64) for g in init_gains))
        ),
    }


def _differences(stored: Any, current: Any, path: str = "") -> list[str]:
    if isinstance(stored, dict) and isinstance(current, dict):
        out = []
        for key in sorted(set(stored) | set(current)):
            where = f"{path}.{key}" if path else str(key)
            if key not in stored:
                out.append(f"{where}: not in the checkpoint, now {current[key]!r}")
            elif key not in current:
                out.append(f"{where}: {stored[key]!r} in the checkpoint, now absent")
            else:
                out.extend(_differences(stored[key], current[key], where))
        return out
    if isinstance(stored, list | tuple) and isinstance(current, list | tuple):
        if list(stored) == list(current):
            return []
        if len(stored) == len(current) and all(not isinstance(s, dict) for s in stored):
            if all(not isinstance(s, list) for s in stored):
                return [f"{path}: checkpoint {list(stored)!r}, now {list(current)!r}"]
        return [f"{path}: checkpoint {_short(stored)}, now {_short(current)}"]
    if stored != current:
        return [f"{path}: checkpoint {stored!r}, now {current!r}"]
    return []


def _short(value: Any) -> str:
    text = json.dumps(value)
    return text if len(text) <= 120 else text[:117] + "..."


def _canonical(document: Any) -> Any:
    """JSON round trip, so that tuples and lists compare equal."""
    return json.loads(json.dumps(document))


# ---------------------------------------------------------------------- checkpoint io


def _write_atomic_bytes(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as handle:
        handle.write(data)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(tmp, path)


def _save_checkpoint(path: Path, state: tuple, meta: dict) -> None:
    leaves = jax.tree.leaves(state)
    arrays = {f"leaf_{i:05d}": np.asarray(leaf) for i, leaf in enumerate(leaves)}
    arrays["meta"] = np.asarray(json.dumps(meta))
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    _write_atomic_bytes(path, buffer.getvalue())


def _read_meta(path: Path) -> dict:
    try:
        with np.load(path) as data:
            return json.loads(str(data["meta"]))
    except (OSError, KeyError, ValueError) as error:
        raise ValueError(f"{path} is not a fojax tune checkpoint ({error})") from None


def _load_state(path: Path, template: tuple) -> tuple:
    leaves, treedef = jax.tree.flatten(template)
    with np.load(path) as data:
        names = sorted(k for k in data.files if k.startswith("leaf_"))
        if len(names) != len(leaves):
            raise ValueError(
                f"{path} holds {len(names)} arrays, this run needs {len(leaves)}: it was "
                "written by another configuration"
            )
        loaded = []
        for name, leaf in zip(names, leaves, strict=True):
            value = data[name]
            if value.shape != np.shape(leaf) or value.dtype != np.asarray(leaf).dtype:
                raise ValueError(
                    f"{path}: array {name} has shape {value.shape} {value.dtype}, this run "
                    f"needs {np.shape(leaf)} {np.asarray(leaf).dtype}"
                )
            loaded.append(jnp.asarray(value))
    return jax.tree.unflatten(treedef, loaded)


def write_history(path: Path, history: list[dict]) -> None:
    """``history.csv`` (atomically): one row per step, :data:`HISTORY_COLUMNS`."""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=HISTORY_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for row in history:
        writer.writerow({k: (repr(v) if isinstance(v, float) else v) for k, v in row.items()})
    _write_atomic_bytes(path, buffer.getvalue().encode())


# ------------------------------------------------------------------------------- run


@dataclasses.dataclass
class PreparedRun:
    """A validated run, nothing written yet (:func:`prepare`)."""

    spec: ProblemSpec
    config: TunerConfig
    init_label: str
    init_gains: Any
    out: Path | None
    resume: bool
    fingerprint: dict
    checkpoint_meta: dict | None


def prepare(
    spec: ProblemSpec,
    config: TunerConfig,
    init_gains: Any,
    init_label: str,
    out: str | os.PathLike | None,
    resume: bool = False,
) -> PreparedRun:
    """Validate a run before anything is compiled or written.

    Raises ``ValueError`` when the initial gains are infeasible or cannot be mapped,
    when ``out`` holds a checkpoint and ``resume`` is false (it is never
    overwritten), when ``resume`` is true and there is no checkpoint, or when the
    checkpoint belongs to another configuration (the message lists what differs).
    """
    from fojax.controllers import registry
    from optimize import params as params_lib

    cls = registry.get_controller_class(spec.controller)
    cls.check_gains(init_gains)
    params_lib.make_parameter_map(spec.controller, spec.fields, spec.share).to_params(init_gains)
    current = _canonical(fingerprint(spec, config, init_label, init_gains))
    meta = None
    if out is not None:
        out = Path(out)
        if out.exists() and not out.is_dir():
            raise ValueError(f"--out {out} exists and is not a directory")
        checkpoint = out / CHECKPOINT
        if resume:
            if not checkpoint.exists():
                raise ValueError(f"nothing to resume: {checkpoint} does not exist")
            meta = _read_meta(checkpoint)
            differences = _differences(meta.get("fingerprint"), current)
            if differences:
                raise ValueError(
                    f"{checkpoint} was written by another configuration; it differs in:\n  "
                    + "\n  ".join(differences)
                    + "\nrerun with the original options, or choose another --out"
                )
        elif checkpoint.exists():
            raise ValueError(
                f"{out} holds the checkpoint of an earlier run ({checkpoint}); pass --resume to "
                "continue it, or choose another --out"
            )
    elif resume:
        raise ValueError("resume needs an output directory")
    return PreparedRun(spec, config, init_label, init_gains, out, resume, current, meta)


def _row(step, result, grad_norm, config, scale, draw_steps, wall) -> dict:
    cost = np.asarray(result.costs.cost, np.float64)
    return {
        "step": step + 1,
        "objective": float(result.objective),
        "mean_cost": float(np.mean(cost)),
        "max_cost": float(np.max(cost)),
        "grad_norm": float(grad_norm),
        "learning_rate": config.learning_rate_at(step),
        "width_scale": scale,
        "diverged": int(np.sum(np.asarray(result.costs.diverged))),
        "bad_gradients": int(result.bad_gradients),
        "draw_steps": int(draw_steps),
        "wall_time_s": round(float(wall), 3),
    }


def tune(
    run: PreparedRun,
    progress: bool = True,
    stop_after: int | None = None,
    callback: Callable[[int, dict, dict], None] | None = None,
    problem: TuningProblem | None = None,
) -> TuneResult:
    """Run (or continue) a prepared tuning run.

    stop_after: stop once this many steps are done in total (an interruption, for
    tests; the checkpoint is written). callback: ``callback(step, params, row)`` after
    each step (its time is not counted in ``wall_time_s``). problem: a
    :class:`TuningProblem` of the same spec and initial gains, to share compiled
    functions.

    With ``run.out``, writes ``checkpoint.npz``, ``history.csv`` and, when all steps
    are done, ``gains.json`` (:func:`fojax.controllers.gains_io.save_gains`).
    """
    spec, config = run.spec, run.config
    if problem is None:
        problem = TuningProblem(spec, run.init_gains)
    optimizer = config.optimizer()
    params = problem.initial_params()
    opt_state = optimizer.init(params)
    state = (params, opt_state)
    history: list[dict] = []
    wall_before = 0.0
    start_step = 0
    checkpoint = run.out / CHECKPOINT if run.out is not None else None
    if run.resume:
        state = _load_state(checkpoint, state)
        meta = run.checkpoint_meta
        start_step = int(meta["step"])
        history = list(meta["history"])
        wall_before = float(meta["wall_time_s"])
        if progress:
            print(f"resuming {checkpoint} at step {start_step}/{config.steps}", file=sys.stderr)
    if run.out is not None:
        run.out.mkdir(parents=True, exist_ok=True)

    @jax.jit
    def update(state, gradient):
        params, opt_state = state
        updates, opt_state = optimizer.update(gradient, opt_state, params)
        return optax.apply_updates(params, updates), opt_state

    def save(step: int) -> None:
        if checkpoint is None:
            return
        wall = history[-1]["wall_time_s"] if history else wall_before
        meta = {
            "fingerprint": run.fingerprint,
            "step": step,
            "history": history,
            "wall_time_s": wall,
        }
        _save_checkpoint(checkpoint, state, meta)
        write_history(run.out / "history.csv", history)

    last = config.steps if stop_after is None else min(config.steps, stop_after)
    step = start_step
    session_start = time.perf_counter()
    excluded = 0.0
    draw_steps = history[-1]["draw_steps"] if history else 0
    try:
        while step < last:
            scale = width_scale(config, step)
            keys = problem.minibatch_keys(step)
            result = problem.value_and_grad(state[0], scale, keys)
            grad_norm = optax.tree.norm(result.gradient)
            new_state = update(state, result.gradient)
            jax.block_until_ready(new_state)
            draw_steps += spec.draw_steps_per_minibatch
            wall = wall_before + time.perf_counter() - session_start - excluded
            row = _row(step, result, grad_norm, config, scale, draw_steps, wall)
            state, step = new_state, step + 1
            history.append(row)
            if progress:
                _print_progress(row, config.steps, wall_before, wall, start_step)
            if callback is not None:
                t0 = time.perf_counter()
                callback(step, state[0], row)
                excluded += time.perf_counter() - t0
            if step % config.checkpoint_every == 0 or step == last:
                save(step)
    except KeyboardInterrupt:
        save(step)
        if progress:
            print(
                f"\ninterrupted after step {step}/{config.steps}; checkpoint written to "
                f"{checkpoint}; run again with --resume to continue",
                file=sys.stderr,
            )
        raise
    if step == start_step:
        save(step)  # nothing to do (a finished run resumed): rewrite the outputs
    params = state[0]
    gains = problem.gains(params)
    if run.out is not None and step == config.steps:
        metadata = {
            "tuned_by": "fojax tune",
            "problem": run.fingerprint["problem"],
            "tuner": run.fingerprint["tuner"],
            "init": run.init_label,
            "steps_done": step,
            "final_objective": history[-1]["objective"] if history else None,
            "draw_steps": history[-1]["draw_steps"] if history else 0,
            "wall_time_s": history[-1]["wall_time_s"] if history else 0.0,
        }
        gains_io.save_gains(run.out / "gains.json", spec.controller, gains, metadata)
    return TuneResult(params, gains, history, step, problem)


def _print_progress(row: dict, total: int, wall_before: float, wall: float, start: int) -> None:
    done = row["step"]
    per_step = (wall - wall_before) / max(done - start, 1)
    left = per_step * (total - done)
    print(
        f"  step {done}/{total}  objective {row['objective']:.4e}  |grad| "
        f"{row['grad_norm']:.3e}  lr {row['learning_rate']:.3g}  width x{row['width_scale']:.3g}"
        f"  diverged {row['diverged']}  {wall:.0f} s (about {left:.0f} s left)",
        file=sys.stderr,
        flush=True,
    )
