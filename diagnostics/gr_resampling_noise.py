"""GR's finite-P bias on the linear-Gaussian system (exact value and gradient known) with the
resampling noise as it is now (xi independent of the sampling noise eps) and as it was until
2026-12-06 (xi = eps: drawn from ``fold_in(key, 1)``, which is eps's own key in jax). Not part
of the harness: the provenance of numbers quoted in the README.

    python diagnostics/gr_resampling_noise.py [estimates=4000]

Prints, per P and variant, the mean value against the exact J (with its z-score) and the
gradient's relative bias per parameter, over ``estimates`` independent keys.
"""

import sys
from unittest import mock

import jax
import numpy as np

import estimators
from estimators import reparameterisation
from estimators.base import draw_noise
from estimators.linear_gaussian import LinearGaussianSystem
from tasks.policies import LinearParams

jax.config.update("jax_enable_x64", True)

SYSTEM = LinearGaussianSystem()
PROBLEM = SYSTEM.problem()
THETA = LinearParams(np.array([[-0.5, -0.8]]), np.array([0.1]))  # tests/test_estimators.py's


def noise_with_xi_equal_to_eps(problem, key, num_particles, dtype):
    """GR's noise as it was: the resampling noise xi is the sampling noise eps itself."""
    s0, eps = draw_noise(problem, key, num_particles, dtype)
    return s0, eps, eps


def main(num_estimates: int) -> None:
    exact_value = float(SYSTEM.objective(THETA))
    exact_grad = np.concatenate([np.ravel(g) for g in jax.tree.leaves(jax.grad(SYSTEM.objective)(THETA))])
    print(f"exact J {exact_value:.4f}, gradient {np.round(exact_grad, 4)}; {num_estimates} estimates each")
    keys = jax.random.split(jax.random.key(0), num_estimates)
    for P in (5, 20):
        for name, noise in (("xi independent (now)", reparameterisation.draw_resampling_noise),
                            ("xi = eps (until 2026-12-06)", noise_with_xi_equal_to_eps)):
            with mock.patch.object(reparameterisation, "draw_resampling_noise", noise):
                e = jax.jit(jax.vmap(lambda k: estimators.make("gr")(PROBLEM, THETA, k, P)))(keys)  # noqa: B023
            values = np.asarray(e.value)
            grads = np.concatenate([np.asarray(g).reshape(num_estimates, -1) for g in jax.tree.leaves(e.grad)], 1)
            z = (values.mean() - exact_value) / (values.std(ddof=1) / np.sqrt(num_estimates))
            bias = (grads.mean(0) - exact_grad) / np.abs(exact_grad)
            print(f"P = {P:2d}, {name:28s}: J {values.mean():.4f} ({100 * (values.mean() / exact_value - 1):+.1f} %, "
                  f"z {z:+.1f}); gradient relative bias {np.round(100 * bias, 1)} %")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 4000)
