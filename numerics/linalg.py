"""Linear algebra that never hands XLA a batched LAPACK call.

jaxlib 0.10.2 (the version pinned here) on CPU runs a batched Cholesky, triangular solve or LU
(batch > 1) by splitting the batch over XLA's intra-op thread pool and blocking until the pieces
finish. When two such calls run concurrently (independent ops in one program: e.g. both
branches of a cond that vmap turned into a select, as in optax's line search) each holds a pool
thread and waits for pieces queued behind the other: a deadlock at 0 % CPU, seen on 2 cores
with ``jax.vmap(gp.train)``, with two independent (8, 64, 64) Choleskys in one jit, and in
learning runs vmapped over repeats. Unbatched calls did not hang (16 concurrent unbatched
Choleskys and solves, 100 runs). Batches appear where one does not write them: ``vmap`` over
seeds or particles, and ``jacfwd`` (a vmap of jvps: the JVP of a Cholesky is a triangular solve
per tangent). Hence two kinds of routine here:

- ``cholesky``, ``solve_lower``, ``solve_lower_t`` (LAPACK, for large matrices such as a GP's
  N x N kernel matrix) are ``custom_vmap``ped: on the CPU a batched matrix is handled by
  ``lax.map`` (a loop of unbatched calls); a shared matrix with a batch of right-hand sides
  becomes ONE call with the batch folded into the columns. On another backend (a GPU: cuSOLVER
  and cuBLAS have no such deadlock, and a loop of small calls wastes the device) a batched
  matrix goes to the batched solver itself (``native_batching``). ``custom_vjp`` gives them reverse-mode derivatives (grad,
  vjp); forward mode (jvp, jacfwd) is not available through them.
- ``solve_det`` (Gauss-Jordan elimination in elementwise ops, no LAPACK call) for small systems:
  the unicycle's 5 x 5 mass matrix, moment matching's D x D matrices, the RBF policy's B x B
  Gram matrix; ``cholesky_small`` and ``solve_triangular_small`` likewise, for MJX's nv x nv
  factorisations (tasks/mjx_dynamics.py). Every transformation applies (vmap, grad, jvp, jacfwd).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

UNROLL_MAX = 8  # solve_det unrolls its elimination loop up to this size (straight-line code)


# ----- LAPACK, never batched on the CPU -----------------------------------------------------------
def native_batching() -> bool:
    """Whether a batch of matrices goes to the backend's batched solver (True off the CPU) rather
    than a ``lax.map`` of unbatched calls (the CPU's workaround); read while tracing."""
    return jax.default_backend() != "cpu"


@jax.custom_vjp
@jax.custom_batching.custom_vmap
def cholesky(a: jax.Array) -> jax.Array:
    """Lower Cholesky factor L (N, N), L L^T = a, of a symmetric positive definite a (N, N);
    NaN where the factorisation fails."""
    return jnp.linalg.cholesky(a)


@cholesky.def_vmap
def _cholesky_vmap(axis_size, in_batched, a):
    return (jnp.linalg.cholesky(a) if native_batching() else jax.lax.map(cholesky, a)), True


def _make_solve(transpose: bool):
    """x = L^-1 b (or L^-T b with ``transpose``), L (N, N) lower triangular, b (N,) or (N, M)."""

    @jax.custom_vjp
    @jax.custom_batching.custom_vmap
    def solve(chol, b):
        return jax.scipy.linalg.solve_triangular(chol, b, lower=True, trans=1 if transpose else 0)

    @solve.def_vmap
    def solve_vmap(axis_size, in_batched, chol, b):
        chol_batched, b_batched = in_batched
        if chol_batched:
            b = b if b_batched else jnp.broadcast_to(b, (axis_size,) + b.shape)
            if native_batching():
                return jax.scipy.linalg.solve_triangular(chol, b, lower=True, trans=1 if transpose else 0), True
            return jax.lax.map(lambda args: solve(*args), (chol, b)), True
        cols = jnp.moveaxis(b, 0, -1).reshape(b.shape[1], -1)  # (N, B*M): one call
        x = solve(chol, cols).reshape(b.shape[1:] + (axis_size,))
        return jnp.moveaxis(x, -1, 0), True

    def fwd(chol, b):
        x = solve(chol, b)
        return x, (chol, x)

    def bwd(res, x_bar):
        # L x = b: b_bar = L^-T x_bar, L_bar = -tril(b_bar x^T); L^T x = b: b_bar = L^-1 x_bar,
        # L_bar = -tril(x b_bar^T).
        chol, x = res
        b_bar = (solve_lower if transpose else solve_lower_t)(chol, x_bar)
        n = chol.shape[0]
        outer = b_bar.reshape(n, -1) @ x.reshape(n, -1).T
        return -jnp.tril(outer.T if transpose else outer), b_bar

    solve.defvjp(fwd, bwd)
    return solve


solve_lower = _make_solve(transpose=False)
solve_lower.__doc__ = "x = L^-1 b: L (N, N) lower triangular, b (N,) or (N, M)."
solve_lower_t = _make_solve(transpose=True)
solve_lower_t.__doc__ = "x = L^-T b: L (N, N) lower triangular, b (N,) or (N, M)."


def _cholesky_fwd(a):
    chol = cholesky(a)
    return chol, chol


def _cholesky_bwd(chol, chol_bar):
    # Transpose of JAX's Cholesky JVP: a_bar = sym(L^-T phi(L^T L_bar) L^-1), phi = lower
    # triangle with the diagonal halved, sym(X) = (X + X^T) / 2.
    p = jnp.tril(chol.T @ chol_bar)
    p = p - 0.5 * jnp.diag(jnp.diag(p))
    s = solve_lower_t(chol, solve_lower_t(chol, p).T).T
    return (0.5 * (s + s.T),)


cholesky.defvjp(_cholesky_fwd, _cholesky_bwd)


# ----- elementwise, every transformation ---------------------------------------------------------
def solve_det(a: jax.Array, b: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(a^-1 b (n, k), det a) for a (n, n) and b (n, k).

    Gauss-Jordan elimination with partial pivoting over the n columns (unrolled for
    n <= ``UNROLL_MAX``); det a is the signed product of the pivots. O(n^3) elementwise work:
    meant for small n (up to a few hundred).
    """
    n = a.shape[0]
    if a.shape != (n, n) or b.ndim != 2 or b.shape[0] != n:
        raise ValueError(f"solve_det needs a (n, n) and b (n, k); got {a.shape} and {b.shape}")
    rows = jnp.arange(n)

    def eliminate(k, carry):
        ab, det = carry
        p = jnp.argmax(jnp.where(rows >= k, jnp.abs(ab[:, k]), -1.0))  # pivot row among k..n-1
        ab = ab[jnp.where(rows == k, p, jnp.where(rows == p, k, rows))]  # swap rows k and p
        det = det * jnp.where(p == k, 1.0, -1.0) * ab[k, k]
        ab = ab - jnp.where(rows == k, 0.0, ab[:, k] / ab[k, k])[:, None] * ab[k]
        return ab, det

    ab = jnp.concatenate([a, b], axis=1)
    ab, det = jax.lax.fori_loop(0, n, eliminate, (ab, jnp.ones((), ab.dtype)), unroll=n <= UNROLL_MAX)
    return ab[:, n:] / jnp.diag(ab[:, :n])[:, None], det


def cholesky_small(a: jax.Array) -> jax.Array:
    """Lower Cholesky factor L (n, n), L L^T = a, of a symmetric positive definite a (n, n), by
    columns: ``v = a[:, j] - L L[j]``, ``L[j, j] = sqrt(v[j])``, ``L[i, j] = v[i] / L[j, j]``
    (i > j); zero above the diagonal, NaN where a is not positive definite. Elementwise ops
    (unrolled for n <= ``UNROLL_MAX``): for small n."""
    a = jnp.asarray(a)
    n = a.shape[0]
    if a.shape != (n, n):
        raise ValueError(f"cholesky_small needs a square matrix; got {a.shape}")
    rows = jnp.arange(n)

    def column(j, chol):
        v = a[:, j] - chol @ chol[j]  # chol[j] holds L[j, :j] so far, zeros after
        pivot = jnp.sqrt(v[j])
        return chol.at[:, j].set(jnp.where(rows > j, v / pivot, jnp.where(rows == j, pivot, 0.0)))

    return jax.lax.fori_loop(0, n, column, jnp.zeros_like(a), unroll=n <= UNROLL_MAX)


def solve_triangular_small(t: jax.Array, b: jax.Array, lower: bool) -> jax.Array:
    """``t^-1 b`` for a triangular t (n, n) (its other triangle is ignored) and b (n,) or
    (n, k), by substitution row by row (forward for ``lower``, else backward). Elementwise ops
    (unrolled for n <= ``UNROLL_MAX``): for small n."""
    n = t.shape[0]
    if t.shape != (n, n) or b.shape[0] != n or b.ndim > 2:
        raise ValueError(f"solve_triangular_small needs t (n, n) and b (n,) or (n, k); got {t.shape} and {b.shape}")
    t = jnp.tril(t) if lower else jnp.triu(t)
    columns = jnp.asarray(b).reshape(n, -1)

    def substitute(step, x):
        i = step if lower else n - 1 - step
        return x.at[i].set((columns[i] - t[i] @ x) / t[i, i])  # rows not yet solved are zero in x

    return jax.lax.fori_loop(0, n, substitute, jnp.zeros_like(columns), unroll=n <= UNROLL_MAX).reshape(b.shape)
