"""Declarative forms of a task's features, cost and policy, so that one definition serves both
a particle (``form(s)``) and PILCO's moment matching (``models.form_moments``,
``estimators.pilco``).

A trig-linear map of a state s (S,) goes through the augmented vector

    y = [s, sin(a_1), cos(a_1), ..., sin(a_K), cos(a_K)],    a = angle_map @ s   (K angles)

and returns ``matrix @ y + offset``. PILCO's sin/cos augmentation, its feature selections and
the points its saturating costs measure (the cart-pole's tip) are all of this form. A
saturating cost is ``1 - exp(-1/2 p^T W p)`` of such a point p (the target folded into the
offset). Arrays are stored as nested tuples so that forms are hashable (static under jit).
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np


def _tuple(array) -> tuple:
    """A 1-D or 2-D array as (nested) tuples of floats."""
    return tuple(tuple(row) if isinstance(row, list) else row for row in np.asarray(array, float).tolist())


class TrigLinearMap(NamedTuple):
    """``matrix @ [s, sin(a_1), cos(a_1), ...] + offset`` with ``a = angle_map @ s``.

    angle_map (K, S), matrix (Q, S + 2K), offset (Q,), as nested tuples."""

    angle_map: tuple
    matrix: tuple
    offset: tuple

    @classmethod
    def make(cls, angle_map, matrix, offset=None) -> TrigLinearMap:
        """From arrays: angle_map (K, S) (K may be 0), matrix (Q, S + 2K), offset (Q,) or None."""
        matrix = np.asarray(matrix, float)
        offset = np.zeros(matrix.shape[0]) if offset is None else offset
        return cls(_tuple(angle_map), _tuple(matrix), _tuple(offset))

    @classmethod
    def select(cls, state_dim: int, angle_dims: tuple[int, ...], keep: tuple[int, ...]) -> TrigLinearMap:
        """The map keeping entries ``keep`` of y, where the angles are the state dimensions
        ``angle_dims`` (so y's entry ``state_dim + 2k`` is sin of angle k, the next its cos)."""
        angles = np.eye(state_dim)[list(angle_dims)].reshape(len(angle_dims), state_dim)
        return cls.make(angles, np.eye(state_dim + 2 * len(angle_dims))[list(keep)])

    @property
    def num_angles(self) -> int:
        return len(self.angle_map)

    def arrays(self, dtype=None):
        """(angle_map (K, S), matrix (Q, S + 2K), offset (Q,)) as arrays."""
        matrix = jnp.asarray(self.matrix, dtype)
        state_dim = matrix.shape[1] - 2 * self.num_angles
        angle_map = jnp.asarray(self.angle_map, dtype).reshape(self.num_angles, state_dim)
        return angle_map, matrix, jnp.asarray(self.offset, dtype)

    def __call__(self, s):
        """The map at one state s (S,) -> (Q,)."""
        angle_map, matrix, offset = self.arrays(s.dtype)
        a = angle_map @ s
        trig = jnp.stack([jnp.sin(a), jnp.cos(a)], axis=-1).reshape(-1)
        return matrix @ jnp.concatenate([s, trig]) + offset


class SaturatingCost(NamedTuple):
    """``c(s) = 1 - exp(-1/2 p^T W p)`` with ``p = point(s)``; weight W (Q, Q) as nested tuples."""

    point: TrigLinearMap
    weight: tuple

    def __call__(self, s):
        p = self.point(s)
        return 1.0 - jnp.exp(-0.5 * p @ jnp.asarray(self.weight, s.dtype) @ p)


class PolicyForm(NamedTuple):
    """A policy as moment matching sees it: ``u = u_max * sat(a)`` (``sat`` PILCO's sine
    saturation; none if u_max is None) with the pre-activation a of the network parameters
    ``net = policy.prepare(theta)``: ``network`` "rbf" (``tasks.policies.RBFNetwork``,
    ``a = sum_i beta_i exp(-1/2 |(f - c_i) / l|^2)``) or "linear" (``LinearParams``,
    ``a = W f + b``)."""

    network: str
    u_max: tuple | None


def with_controls(form: TrigLinearMap, num_controls: int) -> TrigLinearMap:
    """The map of z = [s, u] that returns ``[form(s), u]`` (a GP input from a state's features)."""
    num_angles = form.num_angles
    matrix, offset = np.asarray(form.matrix, float), np.asarray(form.offset, float)
    state_dim = matrix.shape[1] - 2 * num_angles
    angle_map = np.asarray(form.angle_map, float).reshape(num_angles, state_dim)
    angles = np.zeros((num_angles, state_dim + num_controls))
    angles[:, :state_dim] = angle_map
    out = np.zeros((matrix.shape[0] + num_controls, state_dim + num_controls + 2 * num_angles))
    out[:matrix.shape[0], :state_dim] = matrix[:, :state_dim]
    out[:matrix.shape[0], state_dim + num_controls:] = matrix[:, state_dim:]
    out[matrix.shape[0]:, state_dim:state_dim + num_controls] = np.eye(num_controls)
    return TrigLinearMap.make(angles, out, np.concatenate([offset, np.zeros(num_controls)]))
