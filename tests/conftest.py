"""Test configuration: float64 for the whole suite (reference values are checked to 1e-9),
a persistent compilation cache so that every program compiles once per machine, and XLA's
CPU backend set to compile fast: the suite is compile-bound (its programs are small and run
once). Optimisation level 0 (tests/test_learn.py: 143 s -> 100 s) and XLA's older LLVM
emitters for fusions instead of its MLIR fusion emitters (PILCO's finite-difference test:
XLA compiling 28 s -> 11 s, the learning end-to-end test 47 s -> 29 s, one core). A user's
own XLA_FLAGS win over these."""

import json
import os

FAST_COMPILE = {"xla_backend_optimization_level": "0", "xla_cpu_use_fusion_emitters": "false"}
_flags = os.environ.get("XLA_FLAGS", "")
if not _flags or _flags.startswith("--"):
    # before JAX starts its backend; in front, since XLA reads no flag after a token without "--"
    # (and takes XLA_FLAGS not starting with "--" for a file of flags, left as it is)
    _ours = " ".join(f"--{name}={value}" for name, value in FAST_COMPILE.items() if name not in _flags)
    os.environ["XLA_FLAGS"] = f"{_ours} {_flags}".strip()

import jax
import jax.numpy as jnp
import pandas as pd
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update(
    "jax_compilation_cache_dir",
    os.environ.get("JAX_COMPILATION_CACHE_DIR", os.path.join(os.path.dirname(__file__), "..", ".jax_cache")),
)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)

OPTIMISED = {"xla_backend_optimization_level": 2}
"""``jax.jit(..., compiler_options=OPTIMISED)``: XLA's optimisation back for the few test programs that run long
(many particles or keys), where level 0 costs more in running than it saves in compiling (the float32-vs-float64
estimator test's 200 keys of TP: 3.8 s to compile and 25 s to run at level 0, 5.3 s and 4.5 s at level 2)."""

DATA = os.path.join(os.path.dirname(__file__), "data")
"""The reference data (pilco-matlab under Octave), copied with their provenance: data/README.md."""


def reference_path(name: str) -> str:
    """Path of the reference file ``name`` in tests/data (fails with the files there)."""
    path = os.path.join(DATA, name)
    if not os.path.exists(path):
        raise FileNotFoundError(f"no reference file {name!r} in {DATA}; there are {sorted(os.listdir(DATA))}")
    return path


def load_dynamics_vectors(task_name: str) -> pd.DataFrame:
    """The task's reference states, controls, derivatives (``d_*``) and next states (``next_*``)."""
    return pd.read_csv(reference_path(f"{task_name}_dynamics.csv"))


def load_moment_matching_cases() -> list[dict]:
    """PILCO's moment-matching cases (gp0, gp2, gsat, gtrig, loss_sat each)."""
    with open(reference_path("moment_matching.json")) as f:
        return json.load(f)


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
