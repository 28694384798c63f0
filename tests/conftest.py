"""Test configuration: float64 available, persistent compilation cache."""

import os
import pathlib

import jax

jax.config.update("jax_enable_x64", True)
_cache = os.environ.get(
    "FOJAX_TEST_CACHE", str(pathlib.Path(__file__).resolve().parent.parent / ".jax_cache")
)
jax.config.update("jax_compilation_cache_dir", _cache)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
