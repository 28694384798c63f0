"""Test configuration: float64 available, persistent compilation cache."""

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
