"""Argument types shared by the ``fojax`` subcommands: checked before anything compiles.

Each type raises :class:`argparse.ArgumentTypeError` with a message that says what was
wrong and what to give instead; argparse turns it into ``fojax CMD: error: argument
--flag: ...`` and exit status 2. The path checks (:func:`check_output_directory`,
:func:`check_output_file`, :func:`check_input_file`) raise ``ValueError`` for use
outside argparse.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
from argparse import ArgumentTypeError
from pathlib import Path

from fojax import settings
from fojax.settings import (
    CACHE_VARIABLE,
    compile_cache_dir,
    default_cache_dir,
    enable_compile_cache,
    use_host_devices,
)

__all__ = [
    "check_controllers",
    "check_input_file",
    "check_output_directory",
    "check_output_file",
    "controller_flags",
    "enable_dtype",
    "horizon_steps",
    "input_file",
    "listed",
    "nonnegative_float",
    "nonnegative_int",
    "output_directory",
    "output_file",
    "positive_float",
    "positive_floats",
    "positive_int",
    "positive_ints",
    "seed",
    "vehicle_file",
    "reference_file",
    "envelope_file",
    "check_flight",
    "check_reference",
    "describe_reference",
    "describe_vehicle",
    "vehicle_record",
    "add_device_batch",
    "add_options",
    "add_runtime_options",
    "add_study_options",
    "add_infeasible",
    "add_vehicle",
    "check_runtime",
    "CACHE_VARIABLE",
    "compile_cache_dir",
    "default_cache_dir",
    "enable_compile_cache",
    "parse_distributed",
    "setup_runtime",
    "use_host_devices",
]

MAX_SEED = 2**63 - 1
"""Largest seed :func:`jax.random.PRNGKey` takes."""


def _integer(text: str, minimum: int, description: str, maximum: int | None = None) -> int:
    try:
        value = int(text)
    except ValueError:
        hint = ""
        with contextlib.suppress(ValueError):
            number = float(text)
            if math.isfinite(number) and number == int(number):
                hint = f" (write it as {int(number)})"
        raise ArgumentTypeError(f"expected {description}, got {text!r}{hint}") from None
    if value < minimum or (maximum is not None and value > maximum):
        raise ArgumentTypeError(f"expected {description}, got {value}")
    return value


def _real(text: str, allow_zero: bool, description: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ArgumentTypeError(f"expected {description}, got {text!r}") from None
    if not math.isfinite(value) or value < 0 or (value == 0 and not allow_zero):
        raise ArgumentTypeError(f"expected {description}, got {text}")
    return value


def positive_int(text: str) -> int:
    """An integer >= 1."""
    return _integer(text, 1, "a positive integer")


def nonnegative_int(text: str) -> int:
    """An integer >= 0."""
    return _integer(text, 0, "an integer >= 0")


def seed(text: str) -> int:
    """A random seed: an integer in ``[0, 2**63 - 1]``."""
    return _integer(text, 0, f"a seed, an integer >= 0 and <= {MAX_SEED}", MAX_SEED)


def vehicle_file(text: str):
    """argparse type: a vehicle file (TOML, :mod:`fojax.vehicle`), loaded and checked;
    every problem in one message."""
    from fojax import vehicle

    try:
        return vehicle.load(check_input_file(text, "vehicle file"))
    except ValueError as error:  # VehicleError is a ValueError
        raise ArgumentTypeError(str(error)) from None


def reference_file(text: str):
    """argparse type: a reference file (TOML, :mod:`fojax.reference`), loaded and
    checked; every problem in one message."""
    from fojax import reference

    try:
        return reference.load(check_input_file(text, "reference file"))
    except ValueError as error:  # ReferenceError is a ValueError
        raise ArgumentTypeError(str(error)) from None


def envelope_file(text: str):
    """argparse type: an envelope file (TOML, :mod:`fojax.envelope`), loaded and checked;
    every problem in one message."""
    from fojax import envelope

    try:
        return envelope.load(check_input_file(text, "envelope file"))
    except ValueError as error:  # EnvelopeError is a ValueError
        raise ArgumentTypeError(str(error)) from None


def check_reference(parser, reference, horizon: float, option: str = "--horizon") -> dict:
    """The peaks of ``reference`` (waypoints or a built-in, :mod:`fojax.reference`) over
    the run; a usage error (exit 2) when its waypoints leave the horizon (``option``
    sets it) or it asks for a tilt at or beyond the plant's limit (pi/2, where a draw is
    flagged ``tilt_limit``)."""
    if reference is None:
        return {}
    if reference.end is not None and reference.end > horizon + 1e-9:
        parser.error(
            f"--reference: its last waypoint ({reference.end:g} s) is after the end of "
            f"the run ({horizon:g} s); shorten the waypoints or give a longer {option}"
        )
    peaks = reference.peaks(horizon)
    if peaks["tilt"] >= 0.5 * math.pi:
        parser.error(
            f"--reference: its acceleration asks for a tilt of {math.degrees(peaks['tilt']):.0f}"
            " deg, at or beyond the plant's limit of 90 deg; slow the waypoints down"
        )
    return peaks


def check_flight(parser, args, speed_limit: float | None, source: str) -> None:
    """A usage error (exit 2), before anything compiles, when the run's vehicle
    (``args.vehicle``; ``None``: the paper's) cannot hover with its rotors limited to
    ``speed_limit`` rad/s (``source`` names where that limit comes from), or its
    reference file (peaks in ``args.reference_peaks``) asks for more thrust or tilt than
    the vehicle has (:func:`fojax.reference.problems_for`) unless
    ``--allow-infeasible-reference``."""
    from fojax import reference as references
    from fojax import vehicle as vehicles

    flown = getattr(args, "vehicle", None) or vehicles.Vehicle.paper()
    problems = vehicles.hover_problems(flown, speed_limit, source)
    if problems:
        parser.error("the vehicle cannot fly: " + "; ".join(problems))
    peaks = getattr(args, "reference_peaks", None)
    if not peaks or getattr(args, "allow_infeasible_reference", False):
        return
    problems = references.problems_for(peaks, flown, speed_limit)
    if problems:
        parser.error(
            "--reference: " + "; ".join(problems) + ". Slow the waypoints down, or give "
            "--allow-infeasible-reference to fly it anyway"
        )


def add_infeasible(parser) -> None:
    """``--allow-infeasible-reference``."""
    parser.add_argument(
        "--allow-infeasible-reference", action="store_true",
        help="fly a --reference that asks for more thrust or tilt than the vehicle has "
        "(refused by default, naming its peak and the vehicle's limit)",
    )  # fmt: skip


def describe_vehicle(vehicle, speed_limit: float | None) -> str:
    """Two lines: the vehicle (``None``: the paper's) and its authority at ``speed_limit``."""
    from fojax import vehicle as vehicles

    flown = vehicles.Vehicle.paper() if vehicle is None else vehicle
    layout = flown.rotor_layout()
    rotors = {"plus": "'+'", "x": "X"}.get(layout.name, "rotors as listed")
    lag = f", rotors lag {flown.lag() * 1e3:g} ms" if flown.lag() else ""
    return (
        f"vehicle: {flown.description or 'the vehicle file'} (m = {flown.mass:.4g} kg, "
        f"{rotors} at {layout.arm():.4g} m{lag})\n"
        + flown.authority(speed_limit).describe()
    )


def vehicle_record(vehicle, speed_limit: float | None) -> dict:
    """``summary.json``'s ``vehicle``: the file's content (the paper's for ``None``) and its
    authority at ``speed_limit`` (:class:`fojax.rotors.Authority`)."""
    from fojax import vehicle as vehicles

    flown = vehicles.Vehicle.paper() if vehicle is None else vehicle
    return {**flown.to_dict(), **flown.authority(speed_limit).to_dict()}


def describe_reference(reference, peaks: dict) -> str:
    """One line: what the reference is and its peaks."""
    what = (f"{len(reference.times)} waypoints over {reference.end:g} s"
            if reference.end is not None else f"built-in {reference.name}")  # fmt: skip
    return (
        f"reference: {what}; peak speed {peaks['speed']:.3g} m/s, acceleration "
        f"{peaks['acceleration']:.3g} m/s^2 (thrust {peaks['thrust']:.3g} x the weight), tilt "
        f"{math.degrees(peaks['tilt']):.1f} deg"
    )


def add_vehicle(parser) -> None:
    """``--vehicle FILE``: the quadrotor flown (default the paper's)."""
    parser.add_argument(
        "--vehicle", type=vehicle_file, metavar="FILE",
        help="vehicle file (TOML, every quantity with its unit; e.g. "
        "examples/vehicles/paper.toml, docs/model.md); default the paper's quadrotor. "
        "Its rotor speed limit or thrust-to-weight, if any, makes the actuators rotor-limited",
    )  # fmt: skip


def positive_float(text: str) -> float:
    """A finite number > 0 (not nan, not inf)."""
    return _real(text, False, "a finite number > 0")


def nonnegative_float(text: str) -> float:
    """A finite number >= 0 (not nan, not inf)."""
    return _real(text, True, "a finite number >= 0")


def listed(text: str, parse, example: str) -> tuple:
    parts = [part.strip() for part in text.split(",")]
    if not text.strip() or any(not part for part in parts):
        raise ArgumentTypeError(f"expected a comma-separated list like {example}, got {text!r}")
    values = []
    for part in parts:
        try:
            values.append(parse(part))
        except ArgumentTypeError as error:
            raise ArgumentTypeError(
                f"{error} in {text!r} (expected a comma-separated list like {example})"
            ) from None
    return tuple(values)


def positive_ints(text: str) -> tuple[int, ...]:
    """Comma-separated positive integers, e.g. ``1,64,1024``."""
    return listed(text, positive_int, "1,64,1024")


def positive_floats(text: str) -> tuple[float, ...]:
    """Comma-separated finite numbers > 0, e.g. ``0.5,2``."""
    return listed(text, positive_float, "0.5,2")


def scenario_ids(text: str) -> tuple[int, ...]:
    """Comma-separated scenario ids, e.g. ``1,3``: sorted, without repeats."""
    from fojax import scenarios

    try:
        ids = tuple(sorted({int(part) for part in text.split(",") if part.strip()}))
    except ValueError:
        raise ArgumentTypeError(f"expected scenario ids like 1,2,3, got {text!r}") from None
    bad = [i for i in ids if i not in scenarios.SCENARIO_IDS]
    if not ids or bad:
        raise ArgumentTypeError(f"scenarios must be among {scenarios.SCENARIO_IDS}, got {text!r}")
    return ids


def controller_flags(controllers, flags: dict) -> dict[str, list[str]]:
    """Which of ``controllers`` each given flag applies to; ``ValueError`` when one
    does not apply.

    flags: ``{flag: (controller option, value)}`` (e.g. ``{"--switching": ("switching",
    "sat")}``), the value None when the flag was not given (then it is left out). With
    one controller, a flag whose option its law does not take is an error naming the
    law and the options it takes; with several (``--controller all`` or a list), one
    that applies to none of them is, and the answer says which ones each applies to.
    """
    from fojax.controllers import registry

    controllers = list(controllers)
    applied = {}
    for flag, (option, value) in flags.items():
        if value is None:
            continue
        users = [name for name in controllers if option in registry.controller_options(name)]
        if not users:
            takes = ", ".join(sorted(registry.controller_options(controllers[0])))
            if len(controllers) == 1:
                raise ValueError(
                    f"{flag} does not apply to {controllers[0]}, which takes no {option} (its "
                    f"options: {takes}); leave {flag} out"
                )
            raise ValueError(
                f"{flag} applies to none of {', '.join(controllers)} (none takes {option}); "
                f"leave {flag} out"
            )
        applied[flag] = users
    return applied


def check_controllers(parser, names, dt, horizon, fractional, switching) -> None:
    """Build every controller of ``names`` now (each with the options it takes): a bad
    configuration is a ``parser.error`` naming the controller, before compiling."""
    from fojax.controllers import registry

    options = dict(dt=dt, horizon=horizon, fractional_method=fractional, switching=switching)
    for name in names:
        try:
            registry.make_controller(name, **registry.options_for(name, options))
        except ValueError as error:
            parser.error(f"{name}: {error}")


def horizon_steps(parser, horizon: float, dt: float, example: bool = True) -> int:
    """The steps of ``dt`` in ``horizon``; a ``parser.error`` when ``dt`` exceeds it or it
    is not a whole number of steps (``example``: the message suggests a ``--horizon``)."""
    if dt > horizon:
        parser.error(f"--dt ({dt}) must not exceed the horizon ({horizon})")
    steps = horizon / dt
    if abs(steps - round(steps)) > 1e-6 * steps:
        hint = f" s; e.g. --horizon {round(steps) * dt:g}" if example else ""
        parser.error(f"the horizon ({horizon} s) must be a whole number of steps of {dt}{hint}")
    return round(steps)


def enable_dtype(dtype: str) -> None:
    """``--dtype float64`` turns JAX's 64-bit mode on (before any array is made)."""
    if dtype == "float64":
        settings.enable_float64()


# ------------------------------------------------------------------------------ paths


def _path(text: str, what: str) -> Path:
    if not isinstance(text, str | os.PathLike) or not str(text).strip():
        raise ValueError(f"expected {what}, got an empty name {str(text)!r}")
    if "\0" in str(text):
        raise ValueError(f"expected {what}, got a name with a NUL character {str(text)!r}")
    return Path(text).expanduser()


def _existing_ancestor(path: Path) -> Path:
    """The nearest of ``path`` and its parents that exists (``.`` for a relative path)."""
    for candidate in (path, *path.parents):
        with contextlib.suppress(OSError):  # e.g. a name too long
            if candidate.exists():
                return candidate
    return candidate


def check_output_directory(text: str | os.PathLike) -> Path:
    """An output folder that exists or can be created, and can be written to.

    Rejects an empty name, an existing file, a path under a file, a folder without
    write permission, and one that cannot be created. Creates nothing.
    """
    path = _path(text, "an output folder (e.g. results/run1; '.' for this folder)")
    try:
        if path.exists() and not path.is_dir():
            raise ValueError(
                f"{path} is a file, not a folder; choose a folder name for the outputs"
            )
        ancestor = _existing_ancestor(path)
        if not ancestor.is_dir():
            raise ValueError(
                f"{path} cannot be created: {ancestor} is a file; choose a folder that is "
                "not under a file"
            )
        if not os.access(ancestor, os.W_OK | os.X_OK):
            reason = f"{path} cannot be created: no permission to write in {ancestor}"
            if ancestor == path:
                reason = f"cannot write in {path} (permission denied)"
            raise ValueError(f"{reason}; choose a folder you can write to")
        if len(path.name.encode()) > 255:
            raise ValueError(f"{path.name[:40]}... is too long for a file name")
    except OSError as error:
        raise ValueError(f"{path} cannot be used as an output folder: {error}") from None
    return path


def check_output_file(text: str | os.PathLike, example: str = "results/out.json") -> Path:
    """An output file whose folder exists or can be created, and which can be written.

    Rejects an empty name, an existing folder, a path under a file and unwritable
    places. Creates nothing.
    """
    path = _path(text, f"an output file name (e.g. {example})")
    if path.is_dir():
        raise ValueError(f"{path} is a folder; name a file, e.g. {path / Path(example).name}")
    try:
        check_output_directory(path.parent)
    except ValueError as error:
        raise ValueError(f"cannot write {path}: {error}") from None
    if path.exists() and not os.access(path, os.W_OK):
        raise ValueError(f"cannot write {path} (permission denied); choose another file")
    return path


def check_input_file(text: str | os.PathLike, what: str = "file") -> Path:
    """An existing, readable file (not a folder)."""
    path = _path(text, f"a {what}")
    try:
        if not path.exists():
            raise ValueError(f"{what} {path} does not exist")
        if path.is_dir():
            raise ValueError(f"{path} is a folder, not a {what}")
        if not os.access(path, os.R_OK):
            raise ValueError(f"cannot read {what} {path} (permission denied)")
    except OSError as error:
        raise ValueError(f"cannot read {what} {path}: {error}") from None
    return path


def _argparse_type(check, *args):
    def convert(text: str) -> Path:
        try:
            return check(text, *args)
        except ValueError as error:
            raise ArgumentTypeError(str(error)) from None

    convert.__name__ = check.__name__.removeprefix("check_")
    return convert


output_directory = _argparse_type(check_output_directory)
"""argparse type: :func:`check_output_directory`."""

output_file = _argparse_type(check_output_file)
"""argparse type: :func:`check_output_file`."""

input_file = _argparse_type(check_input_file, "gains file")
"""argparse type: an existing, readable gains file (:func:`check_input_file`)."""


# ------------------------------------------------------- compilation and distributed runs


class _Removed(argparse.Action):
    """An option that no longer exists: an error saying what replaced it."""

    def __init__(self, option_strings, dest, replacement: str = "", **kwargs):
        self.replacement = replacement
        super().__init__(option_strings, dest, nargs="?", help=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        parser.error(f"{option_string} was removed: {self.replacement}")


def add_options(parser, *options: tuple[str, dict]) -> None:
    """Add each ``(flag, add_argument keywords)`` to ``parser`` (or an argument group), in
    order: a command's options declared as one table."""
    for flag, keywords in options:
        parser.add_argument(flag, **keywords)


OUTPUT_FOLDER = dict(
    required=True, type=output_directory, metavar="DIR", help="output folder (created if needed)"
)
"""``--out DIR`` of the commands that write a folder of results (``simulate``, ``tune``)."""

STEP = dict(type=positive_float, default=1e-3, help="step, s (1e-3)")
"""``--dt`` of ``simulate`` and ``tune``."""


def add_device_batch(parser: argparse.ArgumentParser) -> None:
    """``--device-batch N``: draws per block, each device's share of a call (and the
    removed ``--chunk``, which now ends in a message saying so)."""
    parser.add_argument(
        "--device-batch",
        type=positive_int,
        metavar="N",
        help="draws each device computes in one call (default: 50 on a CPU, 1024 on a "
        "GPU). Draw i's numbers do not depend on the draw count, the devices or the "
        "processes, only on this block size (rounding); memory grows with it",
    )
    parser.add_argument(
        "--chunk",
        action=_Removed,
        replacement="draws are computed in blocks of --device-batch draws per device "
        "(default 50 on a CPU); give --device-batch N",
    )


def add_study_options(parser: argparse.ArgumentParser, keep: int, keep_help: str) -> None:
    """The options of a command that runs Monte Carlo studies into a folder
    (``simulate``, ``reproduce``): ``--device-batch``, ``--keep`` (default ``keep``),
    ``--dtype``, ``--no-figures``, ``--overwrite`` and ``--quiet``."""
    add_device_batch(parser)
    parser.add_argument("--keep", type=nonnegative_int, default=keep, help=keep_help)
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    parser.add_argument("--no-figures", action="store_true", help="skip the figures")
    parser.add_argument(
        "--overwrite", action="store_true", help="discard chunks of an earlier run in DIR/chunks"
    )
    parser.add_argument("--quiet", action="store_true", help="no progress display")


def add_runtime_options(parser: argparse.ArgumentParser, distributed: bool = True) -> None:
    """The options every command that compiles rollouts shares: the persistent
    compilation cache and, with ``distributed``, joining a ``jax.distributed`` run."""
    group = parser.add_argument_group("compilation and distributed runs")
    group.add_argument(
        "--no-compile-cache",
        action="store_true",
        help=f"neither read nor write the persistent compilation cache (default: on, in "
        f"{default_cache_dir()}; {CACHE_VARIABLE}=0 turns it off, {CACHE_VARIABLE}=DIR "
        "moves it)",
    )
    if not distributed:
        return
    group.add_argument(
        "--coordinator",
        metavar="HOST:PORT",
        help="join a multi-process run (jax.distributed) whose process 0 listens at "
        "HOST:PORT; with --num-processes and --process-id. Without them a run joins "
        "when JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES and JAX_PROCESS_ID are set "
        "(a flag overrides its variable) or a cluster job of several processes is "
        "detected (SLURM srun, Open MPI, ...; docs/distributed.md)",
    )
    group.add_argument("--num-processes", metavar="N", help="processes of the run (>= 1)")
    group.add_argument("--process-id", metavar="I", help="this process's index, 0 to N - 1")


DISTRIBUTED_FLAGS = {
    "coordinator_address": "--coordinator",
    "num_processes": "--num-processes",
    "process_id": "--process-id",
}
"""The flag of each :func:`fojax.sharding.initialize` argument (for its messages)."""


def parse_distributed(values: dict) -> dict:
    """Validated ``{"coordinator_address", "num_processes", "process_id"}`` (None where
    not given) from the options' texts; ``ValueError`` saying what to change.

    Checks each flag's text (``HOST:PORT``, integers, the id below the count). Whether
    the three settings are complete is :func:`fojax.sharding.distributed_settings`'s
    call: a flag left out may come from its ``JAX_*`` variable or a detected cluster job.
    """
    coordinator = values.get("coordinator")
    count = values.get("num_processes")
    index = values.get("process_id")
    try:
        count = None if count is None else _integer(count, 1, "--num-processes, an integer >= 1")
        index = None if index is None else _integer(index, 0, "--process-id, an integer >= 0")
    except ArgumentTypeError as error:
        raise ValueError(str(error)) from None
    if index is not None and count is not None and index >= count:
        raise ValueError(
            f"--process-id must be below the number of processes ({count}), got {index}"
        )
    if coordinator is not None:
        from fojax import sharding

        coordinator = sharding.check_coordinator_address(coordinator, "--coordinator")
    return {"coordinator_address": coordinator, "num_processes": count, "process_id": index}


def check_runtime(argv: list[str], prog: str, distributed: bool = True, environ=None) -> tuple:
    """:func:`setup_runtime`'s checks, which start nothing: ``(parser, options, settings,
    distributed options)``, the runtime options of ``argv`` (``--no-compile-cache`` and,
    with ``distributed``, the flags of a ``jax.distributed`` run, checked by
    :func:`parse_distributed`) and the :class:`fojax.settings.Settings` of ``environ``
    (default ``os.environ``). Bad values exit with status 2 and a message."""
    parser = argparse.ArgumentParser(prog=prog, add_help=False)
    add_runtime_options(parser, distributed)
    known, _ = parser.parse_known_args(argv)
    try:
        found = settings.read(environ)
        options = parse_distributed(vars(known)) if distributed else {}
    except ValueError as error:
        parser.error(str(error))
    return parser, known, found, options


def setup_runtime(argv: list[str], prog: str, distributed: bool = True) -> dict:
    """Before a command touches JAX's devices: turn the compilation cache on (unless
    ``--no-compile-cache``) and join a ``jax.distributed`` run when asked or detected
    (:func:`fojax.sharding.initialize`). Bad values exit with status 2 and a message.

    Returns :func:`fojax.sharding.initialize`'s answer plus ``"compile_cache"`` and
    ``"settings"``, the process's :class:`fojax.settings.Settings`, read here once (a
    variable fojax cannot use exits with status 2 too).
    """
    parser, known, found, options = check_runtime(argv, prog, distributed)
    cache = enable_compile_cache(known.no_compile_cache, found)
    from fojax import sharding

    info = {"process_index": 0, "process_count": 1, "joined": None}
    if distributed:
        try:
            info = sharding.initialize(**options, names=DISTRIBUTED_FLAGS, settings=found)
        except ValueError as error:
            parser.error(str(error))
        except RuntimeError as error:  # e.g. JAX already started in this process
            parser.error(f"cannot join the multi-process run: {error}")
    return {**info, "compile_cache": cache, "settings": found}
