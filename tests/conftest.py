"""Test configuration: float64 for the whole suite (reference values are checked to 1e-9),
and a persistent compilation cache so that MJX compiles once per machine."""

import os

import jax
import jax.numpy as jnp
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update(
    "jax_compilation_cache_dir",
    os.environ.get("JAX_COMPILATION_CACHE_DIR", os.path.join(os.path.dirname(__file__), "..", ".jax_cache")),
)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)

SHARED = os.path.join(os.path.dirname(__file__), "..", "..", "shared")
TESTDATA = os.path.join(SHARED, "testdata")


@pytest.fixture
def unicycle_falling_state():
    """``(z (12,), u (2,))``: a unicycle state from a real run that falls (|theta| passes
    pi/2) within one control period under these controls."""
    z = jnp.array([3.6119, -1.2832, -32.687, 5.0106, 2.9720, -1.5249, 1.4479, 1.4503, -1.4476, 0.0, 0.1302, 0.0])
    return z, jnp.array([9.9333, 43.543])


@pytest.fixture(autouse=True, scope="module")
def release_compiled_programs():
    """Each test module leaves JAX's in-memory caches empty: every compiled program holds
    memory mappings until then, and a process may hold 65530 (Linux's vm.max_map_count; past
    it XLA's compiler fails or segfaults). The suite runs in one process."""
    yield
    jax.clear_caches()
