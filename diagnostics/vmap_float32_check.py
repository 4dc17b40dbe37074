"""Does vmap change float32 estimates beyond round-off under the installed jaxlib? (jaxlib 0.10.2's
CPU backend does: jax-ml/jax#39103.) Not part of the harness: the provenance of the numbers in
the README's jax 0.10.2 entry. Run it under each jaxlib to compare (a venv with ``jax==0.10.1``):

    python diagnostics/vmap_float32_check.py

1. The linear-Gaussian system, BIW-LR at P = 20, 200 keys batched against each key alone: the
   relative error of every estimate's gradient (0.10.2: wrong from index 81, the 82nd key;
   0.10.1: 1.7e-6 at most; 0.10.2 with its YNN reduce fusions off,
   ``XLA_FLAGS=--xla_cpu_experimental_ynn_fusion_type=-reduce``: 1.5e-6, none wrong). Run with
   XLA's default flags otherwise (the tests compile at level 0).
2. The cart-pole on a GP fitted to 60 random transitions, BIW-LR and TP at P = 300 in float32,
   5 keys batched as the learning runs batch seeds (run it with the jobs' XLA_FLAGS): the
   gradient batched against alone, and the effective sample sizes of the first three steps
   against float64. Round-off amplified through exploding particle gradients makes the first
   comparison large under any jaxlib; compare versions, not the number with zero.
"""

import dataclasses
import sys

import jax

jax.config.update("jax_enable_x64", True)  # before anything computes (the tests' module does at import)

import jax.numpy as jnp  # noqa: E402
import jaxlib  # noqa: E402
import numpy as np  # noqa: E402

import estimators  # noqa: E402
from harness.episodic import cast_floating  # noqa: E402

sys.path.insert(0, "tests")
from test_estimators import PROBLEM, THETA, cartpole_gp_problem, flat  # noqa: E402


def batched(est, problem, theta, keys, num_particles):
    """The estimates of ``keys`` vmapped in one jitted program."""
    run = jax.jit(jax.vmap(lambda pr, th, k: est(pr, th, k, num_particles), in_axes=(None, None, 0)))
    return run(problem, theta, keys)


def alone(est, problem, theta, keys, num_particles):
    """Each key's estimate from the unbatched jitted program, stacked as ``batched``'s."""
    run = jax.jit(lambda pr, th, k: est(pr, th, k, num_particles))
    return jax.tree.map(lambda *leaves: jnp.stack(leaves), *[run(problem, theta, k) for k in keys])


def main() -> None:
    print("jax", jax.__version__, "jaxlib", jaxlib.__version__)
    theta32 = cast_floating(THETA, jnp.float32)
    keys = jax.random.split(jax.random.key(0), 200)
    est = estimators.make("biw_lr")
    g_b = flat(batched(est, PROBLEM, theta32, keys, 20).grad, 200).astype(float)
    g_a = flat(alone(est, PROBLEM, theta32, keys, 20).grad, 200).astype(float)
    error = np.abs(g_b - g_a).max(1) / np.abs(g_a).max(1)
    wrong = np.flatnonzero(error > 1e-5)
    print(f"linear-Gaussian, BIW-LR, P = 20, float32, 200 keys: max relative error {error.max():.1e}; "
          f"{len(wrong)} wrong (> 1e-5){f', the first at index {wrong[0]}' if len(wrong) else ''}")

    problem, theta = cartpole_gp_problem()
    problem32 = dataclasses.replace(problem, model_params=cast_floating(problem.model_params, jnp.float32))
    keys = jax.random.split(jax.random.key(1), 5)
    for name in ("biw_lr", "tp"):
        est = estimators.make(name)
        theta32 = cast_floating(theta, jnp.float32)
        b32, a32 = batched(est, problem32, theta32, keys, 300), alone(est, problem32, theta32, keys, 300)
        b64 = batched(est, problem, theta, keys, 300)
        g_b, g_a = flat(b32.grad, 5).astype(float), flat(a32.grad, 5).astype(float)
        per_key = np.abs(g_b - g_a).max(1) / np.abs(g_a).max(1)
        ess = np.abs(np.asarray(b32.aux["ess"], float)[:, :3] / np.asarray(b64.aux["ess"])[:, :3] - 1).max()
        print(f"cart-pole GP, {name}, P = 300, float32, 5 keys: gradient batched vs alone {per_key.min():.2f}-"
              f"{per_key.max():.2f} of its largest entry; first 3 steps' ESS vs float64 {ess:.1e}")


if __name__ == "__main__":
    main()
