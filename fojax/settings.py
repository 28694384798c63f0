"""Process settings: every environment variable fojax reads, and every JAX option it sets.

:func:`read` takes the environment once into a :class:`Settings` (frozen): the
commands read it when they start (:func:`fojax.cli.arguments.setup_runtime`) and pass
it down; a library function given none reads the environment at that call. Nothing
here writes ``os.environ``: the host device count is JAX's ``jax_num_cpu_devices``
option (:func:`use_host_devices`), not an ``XLA_FLAGS`` written behind the user's back.

The variables (an empty one counts as unset):

* ``XLA_FLAGS``: XLA's flags, as the user set them; those that change arithmetic are
  part of a stored run's fingerprint (:func:`fojax.study.numeric_xla_flags`), and one
  that sets ``xla_force_host_platform_device_count`` is the host device count.
* ``FOJAX_COMPILE_CACHE``: ``0`` (``off``, ``false``, ``no``) turns the persistent
  compilation cache off, a folder moves it; default ``$XDG_CACHE_HOME/fojax/jax``
  (``XDG_CACHE_HOME`` default ``~/.cache``). JAX reads ``JAX_COMPILATION_CACHE_DIR``
  itself; a folder chosen that way is kept.
* ``FOJAX_UNION``: ``0`` runs studies that differ only in their scenario each on its
  own (default ``1``: as members of one union of scenarios, :mod:`fojax.cli.study`).
* ``FOJAX_COMPILE_THREADS``: threads compiling a study's programs while earlier runs
  compute (default one per core, at most 4; ``0``: each compiled when its run starts).
* ``JAX_COORDINATOR_ADDRESS``, ``JAX_NUM_PROCESSES``, ``JAX_PROCESS_ID``: a
  multi-process run (:func:`fojax.sharding.distributed_settings` checks them);
  ``SLURM_JOB_ID``, ``SLURM_NTASKS``, ``SLURM_PROCID``: a SLURM job, where JAX's own
  cluster detection is missing.

The JAX options (``jax.config``) fojax sets are set here only: 64-bit mode
(:func:`enable_float64`), the persistent compilation cache
(:func:`enable_compile_cache`; :func:`without_compile_cache` for a block of code) and
the host device count (:func:`use_host_devices`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import sys
from collections.abc import Mapping
from pathlib import Path

__all__ = [
    "CACHE_VARIABLE",
    "DISTRIBUTED_VARIABLES",
    "Settings",
    "backends_started",
    "compile_cache_dir",
    "default_cache_dir",
    "enable_compile_cache",
    "enable_float64",
    "read",
    "use_host_devices",
    "without_compile_cache",
]

CACHE_VARIABLE = "FOJAX_COMPILE_CACHE"
"""Environment variable: ``0`` (or ``off``, ``false``, ``no``) turns the persistent
compilation cache off; a folder name puts it there."""

DISTRIBUTED_VARIABLES = ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID")
"""The environment variables of a :func:`jax.distributed.initialize` run. JAX reads only
the first itself (0.4-0.10); :func:`fojax.sharding.initialize` reads all three."""

SLURM_VARIABLES = ("SLURM_JOB_ID", "SLURM_NTASKS", "SLURM_PROCID")

_OFF = ("0", "off", "false", "no")
_ON = ("", "1", "true", "yes", "on")
HOST_DEVICE_FLAG = "xla_force_host_platform_device_count"


@dataclasses.dataclass(frozen=True)
class Settings:
    """The process's settings, as :func:`read` found them in the environment.

    xla_flags: ``XLA_FLAGS`` (``""`` when unset). cache_home: ``$XDG_CACHE_HOME`` or
    ``~/.cache``. compile_cache: ``FOJAX_COMPILE_CACHE`` as given (``""`` unset).
    union: ``FOJAX_UNION``. compile_threads: ``FOJAX_COMPILE_THREADS`` (None: the
    default, one per core, at most 4). distributed: the texts of
    :data:`DISTRIBUTED_VARIABLES`, None where unset. slurm: those of
    :data:`SLURM_VARIABLES`. cores: the cores this process may run on (its CPU
    affinity: under SLURM, the task's).
    """

    xla_flags: str = ""
    cache_home: Path = dataclasses.field(default_factory=lambda: Path.home() / ".cache")
    compile_cache: str = ""
    union: bool = True
    compile_threads: int | None = None
    distributed: tuple[str | None, str | None, str | None] = (None, None, None)
    slurm: tuple[str | None, str | None, str | None] = (None, None, None)
    cores: int = 1

    @property
    def host_device_flag(self) -> bool:
        """Whether ``XLA_FLAGS`` sets the host device count itself."""
        return HOST_DEVICE_FLAG in self.xla_flags

    @property
    def threads(self) -> int:
        """Threads compiling a study's programs: ``compile_threads``, or one per core
        (at most 4): XLA compiles a program on one thread and a study's programs are
        independent, so they compile side by side (docs/performance.md)."""
        return self.compile_threads if self.compile_threads is not None else min(4, self.cores)


def _usable_cores() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _union(text: str) -> bool:
    text = text.strip().lower()
    if text in _ON:
        return True
    if text in _OFF:
        return False
    raise ValueError(f"FOJAX_UNION must be 0 or 1, got {text!r}")


def _threads(text: str) -> int | None:
    text = text.strip()
    if not text:
        return None
    try:
        value = int(text)
    except ValueError:
        raise ValueError(f"FOJAX_COMPILE_THREADS must be an integer >= 0, got {text!r}") from None
    if value < 0:
        raise ValueError(f"FOJAX_COMPILE_THREADS must be an integer >= 0, got {value}")
    return value


def read(environ: Mapping[str, str] | None = None) -> Settings:
    """:class:`Settings` of ``environ`` (default ``os.environ``, read now); a
    ``ValueError`` naming the variable for a value fojax cannot use."""
    env = os.environ if environ is None else environ
    home = env.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Settings(
        xla_flags=env.get("XLA_FLAGS", ""),
        cache_home=Path(home),
        compile_cache=env.get(CACHE_VARIABLE, "").strip(),
        union=_union(env.get("FOJAX_UNION", "")),
        compile_threads=_threads(env.get("FOJAX_COMPILE_THREADS", "")),
        distributed=tuple(
            env[k] if env.get(k, "").strip() else None for k in DISTRIBUTED_VARIABLES
        ),
        slurm=tuple(env.get(k) or None for k in SLURM_VARIABLES),
        cores=_usable_cores(),
    )


# ------------------------------------------------------------------- JAX's options


def backends_started() -> bool:
    """Whether JAX has made its backends (True when it cannot tell): options such as
    the device count are read then, not when ``jax`` is imported."""
    if "jax" not in sys.modules:
        return False
    try:
        from jax._src import xla_bridge

        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):
        return True


def use_host_devices(requested: int | None = None, settings: Settings | None = None) -> int | None:
    """One CPU device per core (or ``requested``), through JAX's ``jax_num_cpu_devices``,
    unless JAX has started.

    XLA's CPU backend runs one program on one device; with several host devices
    :mod:`fojax.sharding` splits the draws over the cores (``docs/performance.md``,
    design choices). Only the CPU
    platform is affected: on a GPU machine the GPUs stay the default devices. Returns
    the count set, or None when JAX had already started (then nothing changes), or
    when ``XLA_FLAGS`` or an earlier ``jax_num_cpu_devices`` already sets it.
    """
    settings = read() if settings is None else settings
    if backends_started() or settings.host_device_flag:
        return None
    import jax

    if jax.config.jax_num_cpu_devices >= 0:
        return None
    count = requested or settings.cores
    jax.config.update("jax_num_cpu_devices", int(count))
    return count


def enable_float64() -> None:
    """JAX's 64-bit mode on (before any array is made: ``--dtype float64``)."""
    import jax

    jax.config.update("jax_enable_x64", True)


@contextlib.contextmanager
def without_compile_cache():
    """The persistent compilation cache off inside the ``with`` block (every program is
    compiled as a first run on a fresh machine compiles it), as it was after."""
    import jax

    before = jax.config.jax_enable_compilation_cache
    jax.config.update("jax_enable_compilation_cache", False)
    try:
        yield
    finally:
        jax.config.update("jax_enable_compilation_cache", before)


def default_cache_dir(settings: Settings | None = None) -> Path:
    """``$XDG_CACHE_HOME/fojax/jax``, or ``~/.cache/fojax/jax``."""
    settings = read() if settings is None else settings
    return settings.cache_home / "fojax" / "jax"


def compile_cache_dir(disabled: bool = False, settings: Settings | None = None) -> Path | None:
    """Where the commands keep compiled programs: None when ``disabled`` or
    ``FOJAX_COMPILE_CACHE`` says off; that variable's folder when it names one; else
    :func:`default_cache_dir`."""
    settings = read() if settings is None else settings
    text = settings.compile_cache
    if disabled or text.lower() in _OFF:
        return None
    return Path(text).expanduser() if text else default_cache_dir(settings)


def enable_compile_cache(disabled: bool = False, settings: Settings | None = None) -> str | None:
    """Turn JAX's persistent compilation cache on (or off when ``disabled`` or
    ``FOJAX_COMPILE_CACHE=0``); returns the folder in use, or None.

    A folder already chosen (``JAX_COMPILATION_CACHE_DIR``, or by the program calling
    the command, as the test suite does) is kept. A folder that cannot be created is a
    warning: the command runs without the cache.
    """
    import jax

    path = compile_cache_dir(disabled, settings)
    if path is None:
        jax.config.update("jax_enable_compilation_cache", False)
        return None
    jax.config.update("jax_enable_compilation_cache", True)
    chosen = jax.config.jax_compilation_cache_dir
    if chosen:
        return str(chosen)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        print(
            f"warning: no compilation cache ({path} cannot be created: "
            f"{error.strerror or error}); set {CACHE_VARIABLE}=DIR to put it elsewhere",
            file=sys.stderr,
        )
        jax.config.update("jax_enable_compilation_cache", False)
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    # Every program is kept, the small ones too: a warm start of fojax tune compiled
    # ~56 small programs (parameter maps, the optimiser's update, key derivation) of
    # 20-100 ms each before the first step when only rollouts were kept.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return str(path)
