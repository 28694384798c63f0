"""The ``fojax`` command line.

fojax accuracy --out DIR     accuracy and cost of the fractional operators
fojax simulate ...           Monte Carlo study of a scenario (see fojax simulate --help)
fojax reproduce --out DIR    the paper's Section V with Monte Carlo (report, JSON, figures)
fojax tune ...               gain tuning over Monte Carlo draws (see fojax tune --help)
fojax bench [--json FILE]    throughput, compile time and gradient cost
fojax --version              the versions of fojax, Python, jax, jaxlib, optax, numpy

``simulate``, ``reproduce`` and ``tune`` keep compiled programs in a persistent
cache (``~/.cache/fojax/jax``; ``--no-compile-cache`` or ``FOJAX_COMPILE_CACHE=0``
turns it off) and join a multi-process ``jax.distributed`` run when given
``--coordinator``, ``--num-processes`` and ``--process-id``, when JAX's variables are
set, or in a cluster job of several processes (``docs/distributed.md``).

Bad input ends in a message naming what to change and exit status 2, before anything
is compiled. A file-system failure while a command runs (a full disk, a folder removed
under it) ends in a one-line message and exit status 1; an interruption (Ctrl-C) in
exit status 130, with what was finished kept.
"""

from __future__ import annotations

import argparse
import os
import sys

COMMANDS = {
    "accuracy": "accuracy and cost of the fractional operators",
    "reproduce": "the paper's Section V with Monte Carlo: all scenarios and controllers, report",
    "simulate": "Monte Carlo study of a scenario under one or all controllers",
    "bench": "throughput, compile time and gradient cost of the closed loop",
    "tune": "gain tuning over Monte Carlo draws (CMA-ES searches by default; gradient methods)",
}
"""Each command, run by the module ``fojax.cli.<command>``, and what it does."""

HOST_DEVICE_COMMANDS = ("simulate", "reproduce", "tune")
"""Commands whose work is split over one CPU device per core (set before JAX starts;
``XLA_FLAGS=--xla_force_host_platform_device_count=1`` keeps one). ``simulate`` and
``reproduce``: their results do not depend on it (the draws are computed in fixed
blocks, one per device and call, ``--device-batch``, and draw ``i``'s numbers are the
same bit for bit on any number of devices and processes, :mod:`fojax.study`).
``tune``: a population's lanes are split over the devices (on a CPU, one device per
core runs a generation sooner than one device whose kernels are threaded over the
cores); a lane's numbers depend on the lanes per device and call, so the last bits of
a run may differ between machines with other core counts."""


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(
        prog="fojax",
        description="Fractional-order quadrotor control research in JAX.",
        usage="fojax COMMAND [options]   (fojax COMMAND --help for its options)",
    )
    parser.add_argument(
        "command",
        choices=sorted(COMMANDS),
        help=", ".join(f"{name}: {text}" for name, text in sorted(COMMANDS.items())),
    )
    parser.add_argument(
        "--version",
        action="store_true",
        help="print fojax's version and those of Python, jax, jaxlib, optax and numpy",
    )
    if not argv or argv[0] in ("-h", "--help"):
        parser.print_help()
        return 0 if argv else 2
    if argv[0] == "--version":
        from fojax.cli import output

        # fojax 0.1.0 (Python 3.11.7, jax 0.4.38, jaxlib 0.4.38, optax 0.2.4, numpy 2.2.1): what
        # fojax.cli.output.versions records with every run
        named = {"Python" if k == "python" else k: v for k, v in output.versions().items()}
        others = ", ".join(f"{name} {value or 'not installed'}" for name, value in named.items())
        print(f"fojax {output.package_version('fojax') or 'not installed'} ({others})")
        return 0
    args = parser.parse_args(argv[:1])
    if args.command in HOST_DEVICE_COMMANDS:
        from fojax.cli import arguments

        arguments.use_host_devices()
    import importlib

    module = importlib.import_module(f"fojax.cli.{args.command}")
    try:
        status = module.main(argv[1:])
    except KeyboardInterrupt:
        print(f"\nfojax {args.command}: interrupted", file=sys.stderr)
        status = 130
    except OSError as error:
        reason = error.strerror or str(error)
        if error.filename is not None:  # what failed, on which file, and why
            reason = f"cannot write or read {error.filename}: {reason}"
        print(f"fojax {args.command}: error: {reason}", file=sys.stderr)
        status = 1
    return status if isinstance(status, int) else 0


def entry() -> None:
    """The ``fojax`` command (and ``python -m fojax.cli``): :func:`main`, then the
    process's end. A program still compiling for a run that has ended (Ctrl-C, a time
    limit) ends the process at once (``os._exit``), rather than JAX being torn down under
    the compiler (an abort); :func:`main` itself returns, so that it can be called from
    Python (a test, a notebook) without ending the caller."""
    status = main()
    if "fojax.optimize.driver" in sys.modules and sys.modules["fojax.optimize.driver"].compiling():
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)
    sys.exit(status)


def require_extra(command: str, extra: str, modules: tuple[str, ...]) -> None:
    """Exit (status 1) with one line naming the extra that ``fojax command`` needs when
    one of ``modules`` is not installed; call it before doing anything else."""
    import importlib.util

    missing = [name for name in modules if importlib.util.find_spec(name) is None]
    if missing:
        raise SystemExit(
            f"fojax {command}: needs {', '.join(missing)}, in the [{extra}] extra: "
            f"pip install 'fojax[{extra}]'"
        )
