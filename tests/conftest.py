"""Test configuration: float64 available, persistent compilation cache, two tiers.

The default tier runs in minutes; ``--slow`` adds the slow tier (tests marked
``@pytest.mark.slow``: end-to-end studies, multi-process runs, full horizons and the
optimised-compile layout check)."""

import os
import pathlib

# The tests run short horizons, so compilation dominates their time: skip LLVM's
# optimisation passes (compiles about 1.6x faster; the arithmetic is still IEEE, and
# every comparison of two runs is within one build). Set before JAX starts.
_flags = os.environ.get("XLA_FLAGS", "")
if "xla_backend_optimization_level" not in _flags:
    os.environ["XLA_FLAGS"] = f"{_flags} --xla_backend_optimization_level=0".strip()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
_cache = os.environ.get(
    "FOJAX_TEST_CACHE", str(pathlib.Path(__file__).resolve().parent.parent / ".jax_cache")
)
jax.config.update("jax_compilation_cache_dir", _cache)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


def pytest_addoption(parser):
    parser.addoption(
        "--slow",
        action="store_true",
        help="also run the slow tier (end-to-end studies, multi-process runs)",
    )


def pytest_collection_modifyitems(config, items):
    if config.getoption("--slow"):
        return
    slow = [item for item in items if "slow" in item.keywords]
    if slow:
        config.hook.pytest_deselected(items=slow)
        items[:] = [item for item in items if "slow" not in item.keywords]


def close_normwise(got, want, err_msg=""):
    """float32 comparison of two programs that may fuse and round apart: non-finite
    values equal, the largest difference within 1e-4 of the array's largest magnitude
    (a few 1e-5 of a signal's scale were measured on CPUs of different vector widths).
    Import it: ``from conftest import close_normwise``."""
    import numpy as np

    got, want = np.asarray(got, np.float64), np.asarray(want, np.float64)
    finite = np.isfinite(want)
    np.testing.assert_array_equal(got[~finite], want[~finite], err_msg=err_msg)
    got, want = got[finite], want[finite]
    scale = max(float(np.max(np.abs(want), initial=0.0)), 1e-6)
    worst = float(np.max(np.abs(got - want), initial=0.0))
    assert worst <= 1e-4 * scale, f"{err_msg}: max difference {worst:.3g} against scale {scale:.3g}"
