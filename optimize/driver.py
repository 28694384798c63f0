"""The one tuning loop: any strategy on an objective, within a budget, validated,
checkpointed, with a history and progress.

Each step the strategy asks for a request (:class:`fojax.optimize.objective.Request`),
the objective evaluates it, the strategy is told. The budget (:class:`Budget`) counts
steps, evaluated points, simulated draw-steps and seconds; a request that would exceed
a count is not started.

Validation, so that a run never hands back gains worse than its start: the start (step
0), every ``validate_every`` steps (default: once the work since the last validation
reaches :data:`VALIDATION_SHARE` times its own) and the last step, the strategy's
answer is scored on
``validation_draws`` validation draws (disjoint from the tuning and the held-out draws)
at the evaluation law (:meth:`fojax.optimize.objective.Objective.evaluate`); the run
returns the best validated answer (the start wins ties), and says which step it came
from. ``validation_draws=0`` returns the last answer. The start's validation runs in a
thread beside the first steps (it compiles the evaluation program while the first
request's program runs); a program a later phase of the strategy needs
(``strategy.needs()``) is compiled in a thread from the start, beside the first phase.

Checkpoint: every ``checkpoint_every`` steps, at the end and on Ctrl-C, ``DIR/checkpoint.npz``
holds the strategy's state (a pytree of arrays), the best validated point, the
counters, the history and the run's fingerprint, written atomically
(:func:`fojax.records.write_arrays`). A resumed run reloads them and asks the same
requests, so it ends where the uninterrupted run ends, bit for bit; its record keeps the
true start's validation. A checkpoint of another fingerprint is refused with the list of
what differs; nothing is written before every check has passed.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np

from fojax import records
from fojax.optimize import checks
from fojax.optimize.objective import Objective
from fojax.optimize.spec import VALIDATION_OFFSET

__all__ = ["CHECKPOINT", "Budget", "Result", "check_resume", "run"]

CHECKPOINT = "checkpoint.npz"
VALIDATION_SHARE = 8
"""Without ``validate_every``, a validation once the run's work since the last one
(:attr:`fojax.optimize.Evaluation.work`: lane-steps of whole calls, a gradient counted
six times) reaches this many times the validation's own: about the same share of every
method's time."""
FORMAT = 3
COLUMNS = (
    "step",
    "loss",
    "points",
    "mean_target",
    "max_target",
    "grad_norm",
    "width",
    "diverged",
    "bad_gradients",
    "draw_steps",
    "wall_time_s",
    "validation",
    "best_step",
)
"""The columns of every history row (a strategy adds its own after them)."""


@dataclasses.dataclass(frozen=True)
class Budget:
    """Limits of a run (``None``: none): steps (requests), evaluations (points),
    draw_steps (draws x steps simulated), seconds (wall time, checked between steps)."""

    steps: int | None = None
    evaluations: int | None = None
    draw_steps: int | None = None
    seconds: float | None = None

    def __post_init__(self) -> None:
        for name in ("steps", "evaluations", "draw_steps"):
            if getattr(self, name) is not None:
                checks.integer(
                    name,
                    int(getattr(self, name))
                    if isinstance(getattr(self, name), np.integer)
                    else getattr(self, name),
                )
        if self.seconds is not None:
            checks.number("seconds", self.seconds)
        if all(getattr(self, f.name) is None for f in dataclasses.fields(self)):
            raise ValueError("a budget needs a limit: steps, evaluations, draw_steps or seconds")

    def allows(self, used: dict, points: int, draw_steps: int) -> bool:
        """Whether a request of ``points`` and ``draw_steps`` fits after ``used``."""
        return not (
            (self.steps is not None and used["steps"] >= self.steps)
            or (self.evaluations is not None and used["evaluations"] + points > self.evaluations)
            or (self.draw_steps is not None and used["draw_steps"] + draw_steps > self.draw_steps)
            or (self.seconds is not None and used["wall_time_s"] >= self.seconds)
        )


class Result(NamedTuple):
    """x: the returned point ``(d,)`` (the best validated answer; the last one without
    validation). final_x: the last answer. history: one dict per step. steps: steps
    done. best_step: the step ``x`` comes from (0: the start). validation: ``{"draws",
    "switching", "horizon_s", "draw_indices", "initial", "best", "final"}`` (score
    summaries) or ``None``. draw_steps, wall_time_s: what the run spent (every session).
    state: the strategy's last state."""

    x: np.ndarray
    final_x: np.ndarray
    history: list
    steps: int
    best_step: int
    validation: dict | None
    draw_steps: int
    wall_time_s: float
    state: Any


def check_resume(out: str | Path | None, fingerprint: dict, resume: bool) -> dict | None:
    """Before anything compiles: the checkpoint's header when resuming (``ValueError`` when
    there is none, or it was written with another fingerprint), else ``None``
    (``ValueError`` when ``out`` holds a checkpoint: it is never overwritten)."""
    if out is None:
        if resume:
            raise ValueError("resume needs an output directory")
        return None
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} exists and is not a directory")
    path = out / CHECKPOINT
    if not resume:
        if path.exists():
            raise ValueError(
                f"{out} holds the checkpoint of an earlier run ({path}); pass --resume to "
                "continue it, or choose another --out"
            )
        return None
    if not path.exists():
        raise ValueError(f"nothing to resume: {path} does not exist")
    _, header = records.read_arrays(path)
    records.check(header.get("fingerprint") or {}, fingerprint, str(path), earlier="checkpoint")
    return header


class _Run:
    """A run's state between steps (what a checkpoint holds) and its validation."""

    def __init__(self, objective, strategy, x0, fingerprint, out, header, validation, progress):
        self.objective, self.strategy, self.progress = objective, strategy, progress
        self.out = None if out is None else Path(out)
        self.fingerprint = fingerprint
        self.validation_draws, self.validate_every = validation
        self.state, self.best_x = strategy.init(x0), np.asarray(x0, np.float64)
        self.used = {"steps": 0, "evaluations": 0, "draw_steps": 0, "work": 0, "wall_time_s": 0.0}
        self.history: list[dict] = []
        self.best = {"key": None, "step": 0, "initial": None, "best": None, "final": None}
        if header is not None:
            arrays, _ = records.read_arrays(self.out / CHECKPOINT)
            template = {"state": self.state, "best": self.best_x}
            leaves, treedef = jax.tree.flatten(template)
            if len(arrays) != len(leaves) or any(
                a.shape != np.shape(t) or a.dtype != np.asarray(t).dtype
                for a, t in zip(arrays, leaves, strict=True)
            ):
                raise ValueError(f"{self.out / CHECKPOINT} does not hold this run's state")
            restored = jax.tree.unflatten(treedef, arrays)
            self.state, self.best_x = restored["state"], restored["best"]
            self.used, self.history = header["used"], header["history"]
            self.best = {
                **header["validation"],
                "key": tuple(header["validation"]["key"] or ()) or None,
            }
        self.wall_before, self.first_step = self.used["wall_time_s"], self.used["steps"]
        self.session = time.perf_counter()
        self.excluded = 0.0
        self.keys = objective.keys("validation", self.validation_draws) if self.validating else None
        self._last: dict = {}
        self._thread: threading.Thread | None = None
        self._start: dict = {}

    @property
    def validating(self) -> bool:
        return self.validation_draws > 0

    def wall(self) -> float:
        return self.wall_before + time.perf_counter() - self.session - self.excluded

    def score(self, x):
        """``(key, summary)`` of ``x`` on the validation draws (the last one reused)."""
        if "x" in self._last and np.array_equal(x, self._last["x"]):
            return self._last["key"], self._last["summary"]
        key, summary, _ = self.objective.evaluate(x, self.keys)
        self._last = {"x": np.array(x), "key": key, "summary": summary}
        return key, summary

    def start_validation(self, x0) -> None:
        """The start's validation, in a thread (joined by :meth:`join_start`); in a
        multi-process run in line, so that every process runs its programs (and their
        collectives) in the same order."""
        if not self.validating or self.best["initial"] is not None or self._thread is not None:
            return

        def validate():
            try:
                self._start["score"] = self.objective.evaluate(x0, self.keys)[:2]
            except BaseException as error:  # re-raised in the main thread
                self._start["error"] = error

        self._thread = threading.Thread(target=validate, daemon=True)
        if jax.process_count() > 1:
            validate()
        else:
            self._thread.start()

    def join_start(self) -> None:
        if self._thread is None:
            return
        if self._thread.ident is not None:  # started (not run in line)
            self._thread.join()
        self._thread = None
        if "error" in self._start:
            raise self._start["error"]
        key, summary = self._start["score"]
        self.best.update(key=key, step=0, initial=summary, best=summary)
        if self.progress:
            print(f"  start: validation {_headline(summary)}", file=sys.stderr, flush=True)

    def count(self, points: int, evaluation) -> None:
        """Count one request of ``points`` points and its evaluation."""
        self.used["steps"] += 1
        self.used["evaluations"] += points
        self.used["draw_steps"] += evaluation.draw_steps
        self.used["work"] += evaluation.work or evaluation.draw_steps

    def call_back(self, callback, row: dict) -> None:
        """``callback(step, answer, row)``, its time left out of the run's."""
        if callback is not None:
            t0 = time.perf_counter()
            callback(self.used["steps"], self.strategy.answer(self.state), row)
            self.excluded += time.perf_counter() - t0

    def due(self) -> bool:
        """Every ``validate_every`` steps; without it, once the work since the last
        validation reaches :data:`VALIDATION_SHARE` times its own."""
        if self.validate_every is not None:
            return self.used["steps"] % self.validate_every == 0
        own = self.objective.work(self.validation_draws)
        return self.used["work"] - self.best.get("at", 0) >= VALIDATION_SHARE * own

    def validate(self, last: bool) -> dict | None:
        """Validate the answer when due; keep it when it is the best so far."""
        step = self.used["steps"]
        if not self.validating or not (last or self.due()):
            return None
        self.best["at"] = self.used["work"]
        self.join_start()
        x = self.strategy.answer(self.state)
        key, summary = self.score(x)
        if key < self.best["key"]:  # ties keep the earlier
            self.best.update(key=key, step=step, best=summary)
            self.best_x = np.array(x)
        if last:
            self.best["final"] = summary
        return summary

    def save(self) -> None:
        if self.out is None:
            return
        used = {**self.used, "wall_time_s": round(self.wall(), 3)}
        best = {**self.best, "key": list(self.best["key"]) if self.best["key"] else None}
        header = {
            "format": FORMAT,
            "fingerprint": self.fingerprint,
            "used": used,
            "history": self.history,
            "validation": best,
        }
        leaves = jax.tree.leaves({"state": self.state, "best": self.best_x})
        records.write_arrays(self.out / CHECKPOINT, leaves, header)
        columns = list(dict.fromkeys(k for row in self.history for k in row))
        records.write_csv(self.out / "history.csv", self.history, columns)


def _headline(summary: dict) -> str:
    if "yield" in summary:
        return f"yield {summary['yield']:.1%} ({summary['passed']}/{summary['draws']})"
    return f"cost {summary['cost']:.5g}"


def _row(run: _Run, request, evaluation, validation) -> dict:
    outputs, values = evaluation.outputs, np.asarray(evaluation.values, np.float64)
    best = int(np.argmin(np.where(np.isfinite(values), values, np.inf)))
    valid = outputs.valid[best]
    target = outputs.values[best, :, 0][valid]
    row = {
        "step": run.used["steps"],
        "loss": float(values[best]),
        "points": int(values.size),
        "mean_target": float(np.mean(target)) if target.size else math.nan,
        "max_target": float(np.max(target)) if target.size else math.nan,
        "grad_norm": None
        if evaluation.gradient is None
        else float(np.linalg.norm(evaluation.gradient)),
        "width": request.width,
        "diverged": int(np.sum(~outputs.valid)),
        "bad_gradients": evaluation.bad_gradients,
        "draw_steps": run.used["draw_steps"],
        "wall_time_s": round(run.wall(), 3),
        "validation": None if validation is None else _number(validation),
        "best_step": run.best["step"] if run.validating else None,
    }
    return {**row, **run.strategy.row(run.state)}


def _number(summary: dict) -> float:
    return summary["yield"] if "yield" in summary else summary["cost"]


def _compile_ahead(objective: Objective, needs) -> threading.Thread | None:
    """Compile in a thread what the run will need (``needs``: the strategy's ``(kind,
    width)`` pairs, in order): the draws' program beside the first phase's program, then
    a later phase's gradient program beside the first phase's steps. Not in a
    multi-process run (None): compiling ahead runs the programs once, and every process
    must run its programs, collectives included, in the same order."""
    if jax.process_count() > 1:
        return None

    def compile_all():
        first = [threading.Thread(target=_quietly(objective.compile, "sampler"), daemon=True)]
        first.append(threading.Thread(target=_quietly(objective.compile, *needs[0]), daemon=True))
        for thread in first:
            thread.start()
        for thread in first:
            thread.join()
        for kind, width in dict.fromkeys(needs[1:]):
            if kind == "gradient":
                _quietly(objective.compile, kind, width)()

    thread = threading.Thread(target=compile_all, daemon=True)
    thread.start()
    return thread


def _quietly(fn, *args):
    """``fn(*args)`` as a thread's target: an error is left to the call that needs the
    program (it compiles again there and reports it)."""

    def call():
        try:
            fn(*args)
        except Exception:
            pass

    return call


def run(
    objective: Objective,
    strategy,
    budget: Budget,
    x0=None,
    *,
    validation_draws: int = 32,
    validate_every: int | None = None,
    checkpoint_every: int = 10,
    out: str | Path | None = None,
    fingerprint: dict | None = None,
    resume: bool = False,
    progress: bool = True,
    callback: Callable[[int, np.ndarray, dict], None] | None = None,
    stop_after: int | None = None,
) -> Result:
    """Run ``strategy`` on ``objective`` from ``x0`` (default the base gains' point)
    within ``budget`` (module docstring). fingerprint: what the run's numbers depend on
    (default: the objective's, the strategy's and the budget's settings and the start),
    checked on ``resume``. callback: ``callback(step, answer, row)`` after each step (its
    time not counted). stop_after: stop once this many steps are done (an interruption,
    for tests; the checkpoint is written). With ``out``: ``checkpoint.npz`` and
    ``history.csv`` there."""
    checks.integer("validation_draws", validation_draws, 0)
    checks.integer("checkpoint_every", checkpoint_every)
    if validate_every is not None:
        checks.integer("validate_every", validate_every)
    x0 = objective.x0 if x0 is None else np.asarray(x0, np.float64)
    if fingerprint is None:
        fingerprint = describe(objective, strategy, budget, x0, validation_draws, validate_every)
    header = check_resume(out, records.canonical(fingerprint), resume)
    if out is not None:
        Path(out).mkdir(parents=True, exist_ok=True)
    state = _Run(
        objective,
        strategy,
        x0,
        records.canonical(fingerprint),
        out,
        header,
        (validation_draws, validate_every),
        progress,
    )
    warming = _compile_ahead(objective, strategy.needs())
    try:
        last = math.inf if stop_after is None else stop_after
        while state.used["steps"] < last:
            request = strategy.ask(state.state)
            points = np.atleast_2d(request.points).shape[0]
            cost = points * (request.draws or objective.spec.draws) * objective.spec.steps
            if not budget.allows({**state.used, "wall_time_s": state.wall()}, points, cost):
                break
            evaluation = objective(request)
            state.state = strategy.tell(state.state, request, evaluation)
            state.count(points, evaluation)
            state.start_validation(x0)
            done = not _more(budget, state, strategy)
            row = _row(state, request, evaluation, state.validate(done))
            state.history.append(row)
            if progress:
                _print(row, budget, state)
            state.call_back(callback, row)
            if state.used["steps"] % checkpoint_every == 0 or done:
                state.save()
            if done:
                break
    except KeyboardInterrupt:
        state.save()
        if progress:
            print(
                f"\ninterrupted after step {state.used['steps']}; checkpoint written to "
                f"{state.out}; run again with --resume to continue",
                file=sys.stderr,
            )
        raise
    finally:
        if warming is not None:
            warming.join()
    state.start_validation(x0)
    state.join_start()
    finished = not _more(budget, state, strategy)
    if finished and state.history and state.validating and state.best["final"] is None:
        state.validate(True)  # a finished run resumed, or a time budget spent
        state.save()
    return _result(state)


def _more(budget: Budget, state: _Run, strategy) -> bool:
    """Whether the budget allows another request like the next one."""
    request = strategy.ask(state.state)
    points = np.atleast_2d(request.points).shape[0]
    spec = state.objective.spec
    used = {**state.used, "wall_time_s": state.wall()}
    return budget.allows(used, points, points * (request.draws or spec.draws) * spec.steps)


def _result(state: _Run) -> Result:
    final_x = state.strategy.answer(state.state)
    validation = None
    if state.validating:
        validation = {
            "draws": state.validation_draws,
            "switching": state.objective.switching,
            "horizon_s": state.objective.spec.horizon,
            "draw_indices": f"{VALIDATION_OFFSET} + [0, {state.validation_draws})",
            **{k: state.best[k] for k in ("initial", "best", "final")},
            "best_step": state.best["step"],
        }
    x = state.best_x if state.validating else final_x
    best_step = state.best["step"] if state.validating else state.used["steps"]
    return Result(
        x,
        final_x,
        state.history,
        state.used["steps"],
        best_step,
        validation,
        state.used["draw_steps"],
        round(state.wall(), 3),
        state.state,
    )


def describe(objective, strategy, budget, x0, validation_draws, validate_every) -> dict:
    """A run's fingerprint: everything its steps depend on (not the budget: a run resumed
    with a larger one goes on where it stopped)."""
    return {
        "format": FORMAT,
        "objective": objective.describe(),
        "strategy": strategy.settings(),
        "start": np.asarray(x0, np.float64).tolist(),
        "validation": {"draws": validation_draws, "every": validate_every},
    }


def _print(row: dict, budget: Budget, state: _Run) -> None:
    total = budget.steps
    done = row["step"]
    per = (row["wall_time_s"] - state.wall_before) / max(done - state.first_step, 1)
    left = f" (about {per * (total - done):.0f} s left)" if total else ""
    text = f"  step {done}{f'/{total}' if total else ''}  loss {row['loss']:.4e}"
    if row["grad_norm"] is not None:
        text += f"  |grad| {row['grad_norm']:.3e}"
    if row["diverged"]:
        text += f"  diverged {row['diverged']}"
    if row["validation"] is not None:
        text += f"  validation {row['validation']:.4g} (best: step {state.best['step']})"
    print(f"{text}  {row['wall_time_s']:.0f} s{left}", file=sys.stderr, flush=True)
