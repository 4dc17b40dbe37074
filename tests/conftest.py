"""Test configuration: float64 for the whole suite (reference values are checked to 1e-9),
and a persistent compilation cache so that MJX compiles once per machine."""

import os

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update(
    "jax_compilation_cache_dir",
    os.environ.get("JAX_COMPILATION_CACHE_DIR", os.path.join(os.path.dirname(__file__), "..", ".jax_cache")),
)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)

SHARED = os.path.join(os.path.dirname(__file__), "..", "..", "shared")
TESTDATA = os.path.join(SHARED, "testdata")
