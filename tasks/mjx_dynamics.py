"""The true dynamics of a task simulated by MuJoCo MJX (the JAX implementation of MuJoCo).

``mjx_step_fn(task, dtype)`` gives a pure ``step(z, u) -> z_next`` with the meaning of
``task.step``: one control period ``task.dt`` with ``u`` held, on ONE ODE state (``jax.vmap``
does a batch), usable under ``jax.jit`` and differentiable in reverse mode. It simulates
``task.mjcf`` with the model's own integrator and timestep: ``round(task.dt / timestep)``
``mjx.step`` calls in a ``lax.scan``. MuJoCo clamps ``u`` to the actuator's ctrlrange, so the
gradient with respect to a control outside it is zero (``task.step`` does not clamp).

Precision. MJX is not dtype-clean: with ``jax_enable_x64`` on, its float64 NumPy constants
(the RK4 tableau and others) promote float32 data to float64 (``mjx.forward`` returns float64
``qacc``), and ``mjx.step`` with a float32 model and data fails (a scan carry changes dtype).
So the single-state step is traced once, when the dynamics are built, under
``jax.enable_x64(dtype is float64)``, with the model put on device in that mode and the float
leaves of the Model and Data cast to ``dtype``; the resulting jaxpr holds only ``dtype``
floats and is evaluated inside whatever the caller traces. A float32 step is thus float32
throughout (its compiled HLO has no float64 beyond the cast of float64 inputs), also when x64
is on. Building float32 dynamics while x64 is on clears JAX's in-memory caches (see
``mjx_dynamics``): build the dynamics before jitting other work.

Importing this module imports ``mujoco.mjx``, which prints "Failed to import warp" lines on
stdout when warp is not installed (harmless: the JAX implementation is used).
"""

from __future__ import annotations

import contextlib
import dataclasses
import gc
from typing import Any, Callable

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from jax.extend.core import ClosedJaxpr, Jaxpr, jaxpr_as_fun
from mujoco import mjx
from mujoco.mjx._src import forward as mjx_forward
from mujoco.mjx._src import smooth as mjx_smooth
from mujoco.mjx._src import solver as mjx_solver

from numerics import linalg
from tasks.base import Task, check_vector, hold_where

StepFn = Callable[[jax.Array, jax.Array], jax.Array]


def _cast_floats(tree: Any, dtype) -> Any:
    """Cast every floating-point jax.Array leaf of an MJX pytree (Model or Data) to ``dtype``."""

    def cast(leaf):
        if isinstance(leaf, jax.Array) and jnp.issubdtype(leaf.dtype, jnp.floating):
            return leaf.astype(dtype)
        return leaf

    return jax.tree_util.tree_map(cast, tree)


def _own_constants(closed: ClosedJaxpr) -> ClosedJaxpr:
    """``closed`` with every host (NumPy) constant, nested ones included, replaced by a device
    array of its own, in the dtype its abstract value says.

    JAX caches the canonical form of a NumPy constant per array object (MJX's module-level
    RK4 tableau, ...), weakly and without keying on the x64 mode; a jaxpr that keeps such a
    cached value alive makes later traces in the other mode reuse it with the wrong width.
    """

    def own(value, aval):
        if isinstance(value, np.ndarray):  # also JAX's host-side TypedNdArray
            return jax.device_put(np.array(value, dtype=aval.dtype))
        return value

    def fix_param(param):
        if isinstance(param, ClosedJaxpr):
            return fix_closed(param)
        if isinstance(param, Jaxpr):
            return fix_jaxpr(param)
        if type(param) in (tuple, list):
            return type(param)(fix_param(p) for p in param)
        return param

    def fix_jaxpr(jaxpr):
        eqns = [eqn.replace(params={k: fix_param(v) for k, v in eqn.params.items()}) for eqn in jaxpr.eqns]
        return jaxpr.replace(eqns=eqns)

    def fix_closed(closed):
        consts = [own(c, v.aval) for c, v in zip(closed.consts, closed.jaxpr.constvars)]
        return ClosedJaxpr(fix_jaxpr(closed.jaxpr), consts)

    return fix_closed(closed)


class _Overlay:
    """A module seen through: the given attributes replaced, every other one the module's."""

    def __init__(self, module, **replaced):
        self._module = module
        self.__dict__.update(replaced)

    def __getattr__(self, name):
        return getattr(self._module, name)


def _cho_factor(a, lower=False, overwrite_a=False, check_finite=True):
    """``jax.scipy.linalg.cho_factor`` without LAPACK: (factor, lower), the factor's other
    triangle zero."""
    del overwrite_a, check_finite
    chol = linalg.cholesky_small(a)
    return (chol if lower else chol.T), lower


def _cho_solve(c_and_lower, b, overwrite_b=False, check_finite=True):
    """``jax.scipy.linalg.cho_solve`` without LAPACK: ``a^-1 b`` from ``_cho_factor``'s output."""
    del overwrite_b, check_finite
    c, lower = c_and_lower
    chol = c if lower else c.T
    return linalg.solve_triangular_small(chol.T, linalg.solve_triangular_small(chol, b, lower=True), lower=False)


@contextlib.contextmanager
def _traceable_mjx(iterations: int):
    """Within the block (while the step is traced), MJX's modules see two replacements.

    1. The constraint solver runs its iterations in a ``lax.scan`` of length ``iterations``
       that turns into no-ops once converged, instead of a ``lax.while_loop``. The results are
       those of the while loop (and of MuJoCo in C: at most ``opt.iterations``, stopping at
       ``opt.tolerance``), but reverse-mode differentiable: JAX cannot transpose a while loop,
       so MJX itself differentiates only single-iteration solves, which do not converge on
       contacts (tasks/unicycle.xml). MJX's own scan-based loop helper does the iterating (the
       fix proposed upstream, google-deepmind/mujoco#2259).
    2. ``jax.scipy.linalg.cho_factor`` and ``cho_solve`` (the nv x nv mass matrix and Newton's
       Hessian) are the elementwise ``numerics.linalg`` routines. Under ``vmap`` over particles
       the originals become batched LAPACK calls, which can deadlock jaxlib 0.10.2 on CPU
       (``numerics/linalg.py``): a unicycle TP estimate at P = 300 through contact hung at 0 % CPU
       inside two batched triangular solves.

    Only the ``jax`` name of MJX's solver, smooth and forward modules is swapped.
    """

    def bounded_while_loop(cond_fun, body_fun, init_val):
        return mjx_solver._while_loop_scan(cond_fun, body_fun, init_val, iterations)

    scipy = _Overlay(jax.scipy, linalg=_Overlay(jax.scipy.linalg, cho_factor=_cho_factor, cho_solve=_cho_solve))
    replacements = {mjx_solver: _Overlay(jax, lax=_Overlay(jax.lax, while_loop=bounded_while_loop), scipy=scipy),
                    mjx_smooth: _Overlay(jax, scipy=scipy), mjx_forward: _Overlay(jax, scipy=scipy)}
    originals = {module: module.jax for module in replacements}
    for module, replacement in replacements.items():
        module.jax = replacement
    try:
        yield
    finally:
        for module, original in originals.items():
            module.jax = original


def _clear_jax_caches() -> None:
    """Drop JAX's in-memory caches and the cached canonical constants no longer referenced."""
    jax.clear_caches()
    gc.collect()


@dataclasses.dataclass(frozen=True, eq=False)
class MjxDynamics:
    """A task's MuJoCo model on device and its control step, in one float dtype.

    Attributes:
      task: the task whose ``mjcf``, ``dt``, ``to_mujoco`` and ``from_mujoco`` are used.
      model: the ``mjx.Model`` (impl "jax"), float leaves in ``dtype``.
      data0: an ``mjx.Data`` made from ``model``, float leaves in ``dtype``; each control step
        starts from it with ``qpos``, ``qvel`` and ``ctrl`` replaced: no other state is carried
        across control steps (with contact, the constraint solver's warm start restarts each
        control period).
      num_substeps: MJX steps per control period, ``round(task.dt / model.opt.timestep)``.
      dtype: float dtype of the simulation.
      jaxpr: the traced single-state step ``(z (state_dim,), u (control_dim,)) -> z_next``.
    """

    task: Task
    model: mjx.Model
    data0: mjx.Data
    num_substeps: int
    dtype: np.dtype
    jaxpr: ClosedJaxpr

    def step(self, z: jax.Array, u: jax.Array) -> jax.Array:
        """ODE state after one control period with ``u`` held (as ``task.step``).

        z: (state_dim,), u: (control_dim,), cast to ``dtype`` -> (state_dim,) in ``dtype``.
        MuJoCo clamps ``u`` to the actuator's ctrlrange (``task.step`` does not).
        """
        check_vector("z (ODE state)", z, self.task.state_dim)
        check_vector("u (control)", u, self.task.control_dim)
        (z_next,) = jaxpr_as_fun(self.jaxpr)(jnp.asarray(z, self.dtype), jnp.asarray(u, self.dtype))
        return z_next

    __call__ = step


def _raw_step(task: Task, model: mjx.Model, data0: mjx.Data, num_substeps: int, dtype):
    """The untraced control step; trace it under ``jax.enable_x64`` matching ``dtype``.

    As ``task.step``, the substeps stop at the first fallen state (``task.fallen``), which is
    kept for the rest of the period (``hold_where``, stepping the task's initial mean in its
    place): past the fall the model no longer describes the system (the unicycle's joint
    chain locks at |theta| = pi/2, where its yaw and pitch axes align)."""

    def with_state(z, u):
        qpos, qvel = task.to_mujoco(z)
        return data0.replace(qpos=qpos.astype(dtype), qvel=qvel.astype(dtype), ctrl=u.astype(dtype))

    def step(z, u):
        d, safe = with_state(z, u), with_state(task.init_mean.astype(dtype), u)

        def substep(d, _):
            fallen = task.fallen(task.from_mujoco(d.qpos, d.qvel))
            return hold_where(fallen, d, lambda d: mjx.step(model, d), safe), None

        d, _ = jax.lax.scan(substep, d, None, length=num_substeps)
        return task.from_mujoco(d.qpos, d.qvel).astype(dtype)

    return step


def mjx_dynamics(task: Task, dtype=jnp.float64) -> MjxDynamics:
    """Load ``task.mjcf``, put it on device with MJX (impl "jax") in ``dtype``, trace the step.

    Takes a few seconds (tracing MJX); compiling happens where the caller jits. A float32
    build while ``jax_enable_x64`` is on calls ``jax.clear_caches()`` (see below).
    Raises a ValueError when the task has no MuJoCo model, when ``dtype`` is not float32 or
    float64, when float64 is asked for without ``jax_enable_x64``, or when ``task.dt`` is not
    a whole number of the model's timesteps.
    """
    if task.mjcf is None:
        raise ValueError(
            f"task {task.name!r} has no MuJoCo model (its mjcf is None): "
            "MJX dynamics exist only for tasks with an MJCF file"
        )
    dtype = jnp.dtype(dtype)
    if dtype not in (jnp.dtype(jnp.float32), jnp.dtype(jnp.float64)):
        raise ValueError(f"dtype must be float32 or float64; got {dtype}")
    x64 = dtype == jnp.dtype(jnp.float64)
    if x64 and not jax.config.read("jax_enable_x64"):
        raise ValueError("float64 MJX dynamics need jax_enable_x64; enable it or use float32")

    mj_model = mujoco.MjModel.from_xml_path(task.mjcf)
    timestep = float(mj_model.opt.timestep)
    num_substeps = round(task.dt / timestep)
    if num_substeps < 1 or not np.isclose(num_substeps * timestep, task.dt, rtol=1e-9, atol=0.0):
        raise ValueError(
            f"task {task.name!r}: the control period dt = {task.dt} s is not a whole number of "
            f"the MuJoCo timestep {timestep} s of {task.mjcf}"
        )
    # JAX caches the canonical form of each NumPy constant (MJX's RK4 tableau, ...) without
    # keying on the x64 mode: a trace in the other mode would pick up, or leave behind,
    # constants of the wrong width. Such a trace keeps no cached constant (_own_constants)
    # and JAX's caches are cleared around it.
    other_mode = x64 != jax.config.read("jax_enable_x64")
    if other_mode:
        _clear_jax_caches()
    with jax.enable_x64(x64), _traceable_mjx(int(mj_model.opt.iterations)):
        model = _cast_floats(mjx.put_model(mj_model, impl="jax"), dtype)
        data0 = _cast_floats(mjx.make_data(model), dtype)
        jaxpr = jax.make_jaxpr(_raw_step(task, model, data0, num_substeps, dtype))(
            jax.ShapeDtypeStruct((task.state_dim,), dtype),
            jax.ShapeDtypeStruct((task.control_dim,), dtype),
        )
    jaxpr = _own_constants(jaxpr)
    if other_mode:
        _clear_jax_caches()
    return MjxDynamics(task, model, data0, num_substeps, dtype, jaxpr)


def mjx_step_fn(task: Task, dtype=jnp.float64) -> StepFn:
    """A pure ``step(z, u) -> z_next`` simulating ``task.mjcf`` with MJX; see ``MjxDynamics``.

    z: (state_dim,), u: (control_dim,) -> (state_dim,) in ``dtype``, one state
    (``jax.vmap`` for a batch).
    """
    return mjx_dynamics(task, dtype).step
