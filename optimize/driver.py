"""The one tuning loop: any strategy on an objective, within a budget, validated,
checkpointed, with a history and progress.

Each step the strategy asks for a request (:class:`fojax.optimize.Request`), the objective
evaluates it, the strategy is told. The budget (:class:`Budget`) counts steps, evaluated
points, simulated draw-steps and seconds, and may end a converged run (its best
validated score no better by ``tolerance`` over ``patience`` steps); a request that would
exceed a count is not started, nor one that the last request of its kind says would
end past ``seconds``, nor one whose program is still compiling when ``seconds`` come.

Validation, so that a run never hands back gains worse than its start: at the start (step
0), every ``validate_every`` steps (default: once the work since the last validation
reaches :data:`VALIDATION_SHARE` times its own) and at the last step, the strategy's answer
is scored on ``validation_draws`` validation draws (disjoint from the tuning and the
held-out draws) at the evaluation law (:meth:`fojax.optimize.Objective.evaluate`); the run
returns the best validated answer (the start wins ties) and its step; with
``validation_draws=0`` the last answer. The start's validation runs in a thread beside the
first steps; the programs the strategy needs (``strategy.needs()``) are compiled in
threads from the start, from their arguments' shapes (nothing is run to compile them),
and a run that ends does not wait for them.

Host linear algebra (the strategies' NumPy: CMA-ES's eigendecompositions) runs on one
thread during a run (:func:`threadpoolctl.threadpool_limits`): a BLAS library's idle
threads spin beside the devices' threads, which on a CPU hold every core, and slow
every generation of a population search (docs/tuning.md, the driver); the numbers are
the same.

Checkpoint: every ``checkpoint_every`` steps, at the end and on Ctrl-C, ``DIR/checkpoint.npz``
holds the strategy's state (a pytree of arrays), the best validated point, the counters,
the history and the run's fingerprint, written atomically. A step is saved whole or not
at all: Ctrl-C during a step (its evaluation, the strategy's update, its validation)
undoes what the step changed, and the checkpoint holds the run before it. A resumed run
reloads them and asks the same requests, so it ends where the uninterrupted run ends,
bit for bit; its record keeps the true start's validation. A checkpoint of another
fingerprint (other settings, or other code: it holds the digest of fojax's source) is
refused with the list of what differs; nothing is written before every check has passed.
"""

from __future__ import annotations

import contextlib
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
import threadpoolctl

from fojax import records
from fojax.optimize import checks
from fojax.optimize.objective import Objective
from fojax.optimize.spec import VALIDATION_OFFSET

__all__ = ["CHECKPOINT", "Budget", "Result", "check_resume", "compiling", "headline", "run"]

CHECKPOINT = "checkpoint.npz"
VALIDATION_SHARE = 8
"""Without ``validate_every``, a validation once the run's work since the last one
(:attr:`fojax.optimize.Evaluation.work`: lane-steps of whole calls, a gradient counted
six times) reaches this many times the validation's own: about the same share of every
method's time."""
FORMAT = 3
COLUMNS = tuple(
    "step loss points mean_target max_target grad_norm width diverged bad_gradients "
    "draw_steps wall_time_s validation returned_step".split()
)
"""The columns of every history row (a strategy adds its own after them)."""


@dataclasses.dataclass(frozen=True)
class Budget:
    """Limits of a run (``None``: none): steps (requests), evaluations (points),
    draw_steps (draws x steps simulated), seconds (wall time, checked between steps),
    and convergence: ``patience`` steps over which the best validated score improved by
    less than ``tolerance`` (relative) ends the run."""

    steps: int | None = None
    evaluations: int | None = None
    draw_steps: int | None = None
    seconds: float | None = None
    patience: int | None = None
    tolerance: float = 1e-3

    def __post_init__(self) -> None:
        for name in ("steps", "evaluations", "draw_steps", "patience"):
            value = getattr(self, name)
            if value is not None:
                checks.integer(name, int(value) if isinstance(value, np.integer) else value)
        if self.seconds is not None:
            checks.number("seconds", self.seconds)
        checks.number("tolerance", self.tolerance, allow_low=True)
        limits = ("steps", "evaluations", "draw_steps", "seconds")
        if all(getattr(self, name) is None for name in limits):
            raise ValueError("a budget needs a limit: steps, evaluations, draw_steps or seconds")

    def converged(self, scores: list, step: int, since: int = 0) -> bool:
        """Whether the best of ``scores`` (``(step, score)`` of the validations so far,
        lower is better) improved by less than ``tolerance`` (relative) over the last
        ``patience`` steps, ``step`` the steps done; only the scores from step ``since``
        on count (a strategy's phase that may converge, :meth:`_Run.more`)."""
        if self.patience is None or step - since < self.patience:
            return False
        scores = [(at, v) for at, v in scores if at >= since]
        then = [v for at, v in scores if at <= step - self.patience]
        if not then:
            return False
        before, after = min(then), min(v for _, v in scores)
        return before - after <= self.tolerance * abs(before)

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
    done. returned_step: the step ``x`` comes from (0: the start). validation: ``{"draws",
    "switching", "horizon_s", "draw_indices", "initial", "best", "final"}`` (score
    summaries) or ``None``. draw_steps, wall_time_s: what the run spent (every session).
    state: the strategy's last state."""

    x: np.ndarray
    final_x: np.ndarray
    history: list
    steps: int
    returned_step: int
    validation: dict | None
    draw_steps: int
    wall_time_s: float
    state: Any


def check_resume(out: str | Path | None, fingerprint: dict, resume: bool | str) -> dict | None:
    """Before anything compiles: the checkpoint's header when resuming, else ``None``.

    ``resume=True``: ``ValueError`` when there is no checkpoint, or it was written with
    another fingerprint (other settings, or other code: its ``code`` field). ``False``:
    ``ValueError`` when ``out`` holds a checkpoint (it is never overwritten).
    ``"if-same"`` (a study's runs): resume a checkpoint of this fingerprint, start afresh
    where there is none or it is of another (replaced by this run's)."""
    if resume not in (True, False, "if-same"):
        raise ValueError(f"resume must be True, False or 'if-same', got {resume!r}")
    if out is None:
        if resume is True:
            raise ValueError("resume needs an output directory")
        return None
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} exists and is not a directory")
    path = out / CHECKPOINT
    if resume == "if-same":
        if not path.exists():
            return None
        _, header = records.read_arrays(path)
        same = not records.differences(header.get("fingerprint") or {}, fingerprint)
        return header if same else None
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
    advice = (
        "rerun with the original options, or choose another --out (a different `code` is "
        "fojax's source changed since the checkpoint: its run cannot be continued exactly)"
    )
    records.check(
        header.get("fingerprint") or {}, fingerprint, str(path), advice, earlier="checkpoint"
    )
    return header


def headline(summary: dict | None) -> str:
    """A validation or held-out score summary (:meth:`Objective.score`) in a few words."""
    if summary is None:
        return "n/a"
    if summary["kind"] == "yield":
        return f"yield {summary['yield']:.1%} ({summary['passed']}/{summary['draws']})"
    return f"cost {summary['cost']:.5g}"


def _number(summary: dict) -> float:
    return summary["score"]


class _Run:
    """A run's state between steps (what a checkpoint holds), its validation and steps."""

    def __init__(self, objective, strategy, budget, x0, out, fingerprint, header, options):
        self.objective, self.strategy, self.budget = objective, strategy, budget
        self.x0, self.out, self.fingerprint = x0, None if out is None else Path(out), fingerprint
        (self.validation_draws, self.validate_every, self.checkpoint_every, self.progress,
         self.callback) = options  # fmt: skip
        self.state, self.best_x = strategy.init(x0), np.asarray(x0, np.float64)
        self.used = {"steps": 0, "evaluations": 0, "draw_steps": 0, "work": 0, "wall_time_s": 0.0}
        self.history: list[dict] = []
        self.best = {"key": None, "step": 0, "initial": None, "best": None, "final": None}
        self.converged: dict | None = None  # the patience and tolerance it converged under
        if header is not None:
            self._restore(header)
        self.wall_before, self.first_step = self.used["wall_time_s"], self.used["steps"]
        self.session, self.excluded = time.perf_counter(), 0.0
        self.keys = objective.keys("validation", self.validation_draws) if self.validating else None
        self._last, self._start = {}, {}  # the last validation; the start's
        self.durations: dict = {}  # the time of the last request of each kind
        self._thread: threading.Thread | None = None

    def _restore(self, header: dict) -> None:
        arrays, _ = records.read_arrays(self.out / CHECKPOINT)
        leaves, treedef = jax.tree.flatten({"state": self.state, "best": self.best_x})
        if len(arrays) != len(leaves) or any(
            a.shape != np.shape(t) or a.dtype != np.asarray(t).dtype
            for a, t in zip(arrays, leaves, strict=True)
        ):
            raise ValueError(f"{self.out / CHECKPOINT} does not hold this run's state")
        restored = jax.tree.unflatten(treedef, arrays)
        self.state, self.best_x = restored["state"], restored["best"]
        self.used, self.history = header["used"], header["history"]
        key = tuple(header["validation"]["key"] or ()) or None
        self.best = {**header["validation"], "key": key}
        self.converged = header.get("converged")

    def ended_converged(self) -> bool:
        """Whether the run (resumed) had converged under this budget's patience and
        tolerance: it takes no further step, as the uninterrupted run took none."""
        budget = {"patience": self.budget.patience, "tolerance": self.budget.tolerance}
        return self.converged == budget

    @property
    def validating(self) -> bool:
        return self.validation_draws > 0

    def wall(self) -> float:
        return self.wall_before + time.perf_counter() - self.session - self.excluded

    def _kind(self, request) -> tuple:
        """What a request's time depends on: gradient or not, its law, step and lanes."""
        points = np.atleast_2d(request.points).shape[0]
        lanes = points * (request.draws or self.objective.spec.draws)
        return bool(request.gradient), request.width is None, request.dt, lanes

    def fits(self, request) -> bool:
        """Whether the budget allows ``request``; with a time limit, whether it is
        expected to end within it (the last request of its kind took as long)."""
        points, spec = np.atleast_2d(request.points).shape[0], self.objective.spec
        expected = self.durations.get(self._kind(request), 0.0)
        used = {**self.used, "wall_time_s": self.wall() + expected}
        steps = spec.steps_at(request.dt)
        return self.budget.allows(used, points, points * (request.draws or spec.draws) * steps)

    def ready(self, request) -> bool:
        """Whether the program ``request`` needs is compiled, waiting for a compilation
        ahead (:func:`_compile_ahead`) at most until the time limit: a run never waits
        past ``seconds`` for a program, and Ctrl-C interrupts the wait."""
        if self.budget.seconds is None:
            return True
        return self.objective.ready(request, max(self.budget.seconds - self.wall(), 0.0))

    def more(self) -> bool:
        """Whether the budget allows another request like the next one, and the run has
        not converged (:meth:`Budget.converged`)."""
        initial = self.best["initial"]
        sign = -1.0 if initial is not None and initial["kind"] == "yield" else 1.0
        scores = [(r["step"], sign * r["validation"]) for r in self.history
                  if r["validation"] is not None]  # fmt: skip
        since = getattr(self.strategy, "settling", lambda state: 0)(self.state)
        if since is not None and self.budget.converged(scores, self.used["steps"], since):
            self.converged = {"patience": self.budget.patience, "tolerance": self.budget.tolerance}
            return False
        return self.fits(self.strategy.ask(self.state))

    def score(self, x):
        """``(key, summary)`` of ``x`` on the validation draws (the last one reused)."""
        if "x" in self._last and np.array_equal(x, self._last["x"]):
            return self._last["key"], self._last["summary"]
        key, summary, _ = self.objective.evaluate(x, self.keys)
        self._last = {"x": np.array(x), "key": key, "summary": summary}
        return key, summary

    def start_validation(self) -> None:
        """The start's validation, in a thread (joined by :meth:`join_start`); in a
        multi-process run in line, so that every process runs its programs (and their
        collectives) in the same order."""
        if not self.validating or self.best["initial"] is not None or self._thread is not None:
            return

        def validate():
            try:
                self._start["score"] = self.objective.evaluate(self.x0, self.keys)[:2]
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
            print(f"  start: validation {headline(summary)}", file=sys.stderr, flush=True)

    def due(self) -> bool:
        """Every ``validate_every`` steps; without it, once the work since the last
        validation reaches :data:`VALIDATION_SHARE` times its own."""
        if self.validate_every is not None:
            return self.used["steps"] % self.validate_every == 0
        own = self.objective.work(self.validation_draws)
        return self.used["work"] - self.best.get("at", 0) >= VALIDATION_SHARE * own

    def validate(self, last: bool) -> dict | None:
        """Validate the answer when due; keep it when it is the best so far."""
        if not self.validating or not (last or self.due()):
            return None
        self.best["at"] = self.used["work"]
        self.join_start()
        x = self.strategy.answer(self.state)
        key, summary = self.score(x)
        if key < self.best["key"]:  # ties keep the earlier
            self.best.update(key=key, step=self.used["steps"], best=summary)
            self.best_x = np.array(x)
        if last:
            self.best["final"] = summary
        return summary

    @contextlib.contextmanager
    def whole(self):
        """Undo what the block changed of the run's record (the strategy's state, the
        best point, the counters, the history, the validation's record, convergence)
        when an exception (Ctrl-C) cuts it: a checkpoint then holds the run before it,
        and a resumed run takes it again, as the uninterrupted run took it once."""
        before = (self.state, self.best_x, dict(self.used), len(self.history), dict(self.best),
                  self.converged)  # fmt: skip
        try:
            yield
        except BaseException:
            self.state, self.best_x, self.used, count, self.best, self.converged = before
            del self.history[count:]
            raise

    def step(self, request) -> bool:
        """Evaluate ``request``, tell the strategy, record, validate and checkpoint;
        whether the budget is spent. The step counts once its row is recorded
        (:meth:`whole`)."""
        began = time.perf_counter()
        with self.whole():
            evaluation = self.objective(request)
            self.state = self.strategy.tell(self.state, request, evaluation)
            self.durations[self._kind(request)] = time.perf_counter() - began
            self.used["steps"] += 1
            self.used["evaluations"] += np.atleast_2d(request.points).shape[0]
            self.used["draw_steps"] += evaluation.draw_steps
            self.used["work"] += evaluation.work or evaluation.draw_steps
            self.start_validation()
            done = not self.more()
            row = self.row(request, evaluation, self.validate(done))
            self.history.append(row)
        if self.progress:
            self.print(row)
        if self.callback is not None:  # its time left out of the run's
            t0 = time.perf_counter()
            self.callback(self.used["steps"], self.strategy.answer(self.state), row)
            self.excluded += time.perf_counter() - t0
        if self.used["steps"] % self.checkpoint_every == 0 or done:
            self.save()
        return done

    def row(self, request, evaluation, validation) -> dict:
        outputs, values = evaluation.outputs, np.asarray(evaluation.values, np.float64)
        best = int(np.argmin(np.where(np.isfinite(values), values, np.inf)))
        target = outputs.values[best, :, 0][outputs.valid[best]]
        gradient = evaluation.gradient
        row = (
            self.used["steps"],
            float(values[best]),
            int(values.size),
            float(np.mean(target)) if target.size else math.nan,
            float(np.max(target)) if target.size else math.nan,
            None if gradient is None else float(np.linalg.norm(gradient)),
            request.width,
            int(np.sum(~outputs.valid)),
            evaluation.bad_gradients,
            self.used["draw_steps"],
            round(self.wall(), 3),
            None if validation is None else _number(validation),
            self.best["step"] if self.validating else None,
        )
        return {**dict(zip(COLUMNS, row, strict=True)), **self.strategy.row(self.state)}

    def print(self, row: dict) -> None:
        total, done = self.budget.steps, row["step"]
        per = (row["wall_time_s"] - self.wall_before) / max(done - self.first_step, 1)
        left = f" (about {per * (total - done):.0f} s left)" if total else ""
        text = f"  step {done}{f'/{total}' if total else ''}  loss {row['loss']:.4e}"
        if row["grad_norm"] is not None:
            text += f"  |grad| {row['grad_norm']:.3e}"
        if row["diverged"]:
            text += f"  diverged {row['diverged']}"
        if row["validation"] is not None:
            text += f"  validation {row['validation']:.4g} (best: step {self.best['step']})"
        print(f"{text}  {row['wall_time_s']:.0f} s{left}", file=sys.stderr, flush=True)

    def save(self) -> None:
        if self.out is None:
            return
        header = {
            "format": FORMAT,
            "fingerprint": self.fingerprint,
            "used": {**self.used, "wall_time_s": round(self.wall(), 3)},
            "history": self.history,
            "converged": self.converged,
            "validation": {
                **self.best,
                "key": list(self.best["key"]) if self.best["key"] else None,
            },
        }
        leaves = jax.tree.leaves({"state": self.state, "best": self.best_x})
        records.write_arrays(self.out / CHECKPOINT, leaves, header)
        columns = list(dict.fromkeys(k for row in self.history for k in row))
        records.write_csv(self.out / "history.csv", self.history, columns)

    def result(self) -> Result:
        """The start's validation joined, the last validation of a finished run that has
        none (resumed finished, or a time budget spent), and the :class:`Result`."""
        self.start_validation()
        self.join_start()
        finished = not self.more()
        if finished and self.history and self.validating and self.best["final"] is None:
            with self.whole():
                self.validate(True)
            self.save()
        final_x, validation = self.strategy.answer(self.state), None
        if self.validating:
            validation = {
                "draws": self.validation_draws,
                "switching": self.objective.switching,
                "horizon_s": self.objective.spec.horizon,
                "draw_indices": f"{VALIDATION_OFFSET} + [0, {self.validation_draws})",
                **{k: self.best[k] for k in ("initial", "best", "final")},
                "returned_step": self.best["step"],
            }
        x = self.best_x if self.validating else final_x
        best = self.best["step"] if self.validating else self.used["steps"]
        return Result(
            x, final_x, self.history, self.used["steps"], best, validation,
            self.used["draw_steps"], round(self.wall(), 3), self.state,
        )  # fmt: skip


def _compile_ahead(objective: Objective, needs, validating: bool) -> threading.Thread | None:
    """Compile in threads what the run will need (``needs``: the strategy's ``(kind,
    width[, dt])``, in order), from the shapes of their arguments, running nothing
    (:meth:`Objective.compile`): the draws' programs and the first phase's program side
    by side, then (``validating``) the validation's (the evaluation law at the spec's
    step: the start's validation after the first step and the run's last validation,
    which a time limit waits for, need it), then a later phase's. The threads are not
    waited for: a request whose
    program is still compiling waits for it (:meth:`_Run.ready`), and a run that ends
    (its budget, Ctrl-C) leaves them behind. Not in a multi-process run (None): every
    process must run its programs, collectives included, in the same order. An error
    is left to the call that needs the program (it compiles again there and reports
    it)."""
    if jax.process_count() > 1 or not needs:
        return None
    needs = [tuple(need) + (None,) * (3 - len(need)) for need in needs]
    samplers = [("sampler", None, dt) for dt in dict.fromkeys(dt for _, _, dt in needs)]
    first = samplers + [needs[0]]
    later = [("sampler", None, None), ("forward", None, None)] if validating else []
    later = [need for need in dict.fromkeys(later + needs[1:]) if need not in first]
    for kind, width, dt in first + later:
        objective.expect(kind, width, dt)  # waited for from now on (:meth:`_Run.ready`)

    def quietly(*args):
        try:
            objective.compile(*args)
        except Exception:
            pass

    def compile_all():
        threads = [threading.Thread(target=quietly, args=a, name=COMPILING, daemon=True)
                   for a in first]  # fmt: skip
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        for need in later:
            quietly(*need)

    thread = threading.Thread(target=compile_all, name=COMPILING, daemon=True)
    thread.start()
    return thread


COMPILING = "fojax-compile-ahead"
"""The name of the threads of :func:`_compile_ahead`."""


def compiling() -> bool:
    """Whether a program is still being compiled ahead for a run that has ended (a
    process that exits meanwhile must not tear JAX down under it: :func:`fojax.cli.main`
    ends such a process at once, its outputs flushed)."""
    return any(t.name == COMPILING and t.is_alive() for t in threading.enumerate())


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
    resume: bool | str = False,
    progress: bool = True,
    callback: Callable[[int, np.ndarray, dict], None] | None = None,
    stop_after: int | None = None,
) -> Result:
    """Run ``strategy`` on ``objective`` from ``x0`` (default the base gains' point)
    within ``budget`` (module docstring). fingerprint: what the run's numbers depend on
    (default: :func:`describe`), checked on ``resume``. callback: ``callback(step,
    answer, row)`` after each step (its time not counted). stop_after: stop once this
    many steps are done (an interruption, for tests; the checkpoint is written). With
    ``out``: ``checkpoint.npz`` and ``history.csv`` there."""
    checks.integer("validation_draws", validation_draws, 0)
    checks.integer("checkpoint_every", checkpoint_every)
    if validate_every is not None:
        checks.integer("validate_every", validate_every)
    x0 = objective.x0 if x0 is None else np.asarray(x0, np.float64)
    if fingerprint is None:
        fingerprint = describe(objective, strategy, budget, x0, validation_draws, validate_every)
    fingerprint = records.canonical(fingerprint)
    header = check_resume(out, fingerprint, resume)
    if out is not None:
        Path(out).mkdir(parents=True, exist_ok=True)
    options = (validation_draws, validate_every, checkpoint_every, progress, callback)
    state = _Run(objective, strategy, budget, x0, out, fingerprint, header, options)
    _compile_ahead(objective, strategy.needs(), validation_draws > 0)
    try:
        with threadpoolctl.threadpool_limits(1, user_api="blas"):
            result = _loop(state, strategy, stop_after)
    except KeyboardInterrupt:
        state.save()
        if progress:
            print(
                f"\ninterrupted after step {state.used['steps']}; checkpoint written to "
                f"{state.out}; run again with --resume to continue",
                file=sys.stderr,
            )
        raise
    return result


def _loop(state: _Run, strategy, stop_after: int | None) -> Result:
    """The steps of :func:`run` until the budget, convergence or ``stop_after``."""
    # a run resumed after it converged takes no further step (its convergence is
    # judged before its last validation: judged again now it could differ)
    finished = state.ended_converged()
    last = math.inf if stop_after is None else stop_after
    while not finished and state.used["steps"] < last:
        request = strategy.ask(state.state)
        if not state.fits(request) or not state.ready(request) or state.step(request):
            break
    return state.result()


def describe(objective, strategy, budget, x0, validation_draws, validate_every) -> dict:
    """A run's fingerprint: everything its steps depend on (not the budget: a run resumed
    with a larger one goes on where it stopped)."""
    return {
        "format": FORMAT,
        "objective": objective.describe(),
        "strategy": strategy.settings(),
        "start": np.asarray(x0, np.float64).tolist(),
        "validation": {"draws": validation_draws, "every": validate_every},
        "code": records.code_digest(),
    }
