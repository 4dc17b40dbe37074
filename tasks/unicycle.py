"""Unicycle balancing (PIPPS paper; PILCO `scenarios/unicycle`, physics by D. Forster).

ODE state (12) ``z = [dtheta, dphi, dpsiw, dpsif, dpsit, x, y, theta, phi, psiw, psif, psit]``
(theta roll, phi yaw, psiw wheel, psif frame pitch, psit turntable; (x, y) the contact point);
controls ``u = [V, U]`` (turntable torque, wheel torque). Modelled state (10)
``s = [dtheta, dphi, dpsiw, dpsif, dpsit, xc, yc, theta, phi, psif]`` with the contact point in
the yawed frame. Equations: pilco-matlab's unicycle (D. Forster's derivation).
"""

from __future__ import annotations

import dataclasses
import os
from typing import ClassVar

import jax.numpy as jnp
import numpy as np

from numerics.linalg import solve_det
from tasks.base import Task, check_vector
from tasks.forms import SaturatingCost, TrigLinearMap
from tasks.policies import Policy, linear_policy

# Physical parameters (SI), from the spec.
mt, mw, mf = 10.0, 1.0, 23.5  # turntable, wheel, frame masses
rw = 0.225  # wheel radius
rf = 0.54  # frame centre of mass to wheel
rt = 0.27  # frame centre of mass to turntable
r = rf + rt  # wheel to turntable
Cw, Aw = 0.0484, 0.0242  # wheel inertia about / perpendicular to the axle
Cf, Bf, Af = 0.8292, 0.4608, 0.4248  # frame inertia
Ct, At = 0.2, 1.3  # turntable inertia about / perpendicular to its axle
g = 9.82

COST_WHEEL_RADIUS = 0.22  # rw_c
COST_FRAME_LENGTH = 0.81  # r_c


def _equations_of_motion(z, u):
    """The 5 x 5 matrix A(theta, psif) and vector b(z, V, U) with ``A zddot = -b``
    for ``zddot = [thetaddot, phiddot, psiwddot, psifddot, psitddot]`` (friction torque T = 0).
    Transcribed term by term from the spec's equations."""
    dtheta, dphi, dpsiw, dpsif, dpsit = z[0], z[1], z[2], z[3], z[4]
    theta, psif = z[7], z[10]
    V, U = u[0], u[1]
    st, ct, sf, cf = jnp.sin(theta), jnp.cos(theta), jnp.sin(psif), jnp.cos(psif)
    a11 = -Ct*sf
    a12 = Ct*cf*ct
    a13 = 0
    a14 = 0
    a15 = Ct
    a21 = 0
    a22 = Cw*st+At*st-rf*(-mf*(st*rf+cf*st*rw)-mt*(st*r+cf*st*rw))+rt*mt*(st*r+cf*st*rw)
    a23 = -cf*rw*(rf*(mf+mt)+rt*mt)
    a24 = -Cw-At-rf*(mf*rf+mt*r)-rt*mt*r
    a25 = 0
    a31 = cf*(-Af*sf-Ct*sf)-sf*(-Bf*cf-At*cf+rf*(-mf*(cf*rf+rw)-mt*(cf*r+rw))-rt*mt*(cf*r+rw))
    a32 = Aw*ct+cf*(Af*cf*ct+Ct*cf*ct)-sf*(-Bf*sf*ct-At*sf*ct+rf*(-mf*sf*ct*rf-mt*sf*ct*r)-rt*mt*sf*ct*r)
    a33 = 0
    a34 = 0
    a35 = Ct*cf
    a41 = -Aw-rw*(mf*(cf*rf+rw)+mw*rw+mt*(cf*r+rw))+sf*(-Af*sf-Ct*sf)+cf*(-Bf*cf-At*cf+rf*(-mf*(cf*rf+rw)-mt*(cf*r+rw))-rt*mt*(cf*r+rw))
    a42 = -rw*(mt*sf*ct*r+mf*sf*ct*rf)+sf*(Af*cf*ct+Ct*cf*ct)+cf*(-Bf*sf*ct-At*sf*ct+rf*(-mf*sf*ct*rf-mt*sf*ct*r)-rt*mt*sf*ct*r)
    a43 = 0
    a44 = 0
    a45 = Ct*sf
    a51 = 0
    a52 = 2*Cw*st+At*st-rf*(-mt*(st*r+cf*st*rw)-mf*(st*rf+cf*st*rw))+rt*mt*(st*r+cf*st*rw)+rw*(mw*st*rw+sf*(mf*sf*st*rw+mt*sf*st*rw)+cf*(mt*(st*r+cf*st*rw)+mf*(st*rf+cf*st*rw)))
    a53 = -Cw-rt*mt*cf*rw+rw*(-mw*rw+sf*(-mf*sf*rw-mt*sf*rw)+cf*(-mf*cf*rw-mt*cf*rw))-rf*(mt*cf*rw+mf*cf*rw)
    a54 = -Cw-At-rf*(mf*rf+mt*r)-rt*mt*r-rw*cf*(mf*rf+mt*r)
    a55 = 0
    b1 = -V+Ct*(-dphi*sf*dpsif*ct-dphi*cf*st*dtheta-cf*dpsif*dtheta)
    b2 = -U+Cw*dphi*ct*dtheta-(-dphi*cf*ct+sf*dtheta)*Bf*(dphi*sf*ct+cf*dtheta)+(dphi*sf*ct+cf*dtheta)*Af*(-dphi*cf*ct+sf*dtheta)+At*dphi*ct*dtheta-(dphi*sf*ct+cf*dtheta)*Ct*(dphi*cf*ct-sf*dtheta+dpsit)+(dphi*cf*ct-sf*dtheta)*At*(dphi*sf*ct+cf*dtheta)-rf*(-mf*g*sf*ct-mf*(sf*dpsif*(-dphi*st+dpsiw)*rw+cf*dphi*ct*dtheta*rw-(-dphi*cf*ct+sf*dtheta)*(dtheta*rw+(dphi*sf*ct+cf*dtheta)*rf)+dphi*ct*dtheta*rf-(-dphi*st+dpsif)*sf*(-dphi*st+dpsiw)*rw)-mt*g*sf*ct-mt*(sf*dpsif*(-dphi*st+dpsiw)*rw+cf*dphi*ct*dtheta*rw-(-dphi*st+dpsif)*sf*(-dphi*st+dpsiw)*rw+dphi*ct*dtheta*(rf+rt)+(dphi*cf*ct-sf*dtheta)*(dtheta*rw+(dphi*sf*ct+cf*dtheta)*(rf+rt))))-rt*(-mt*g*sf*ct-mt*(sf*dpsif*(-dphi*st+dpsiw)*rw+cf*dphi*ct*dtheta*rw-(-dphi*st+dpsif)*sf*(-dphi*st+dpsiw)*rw+dphi*ct*dtheta*(rf+rt)+(dphi*cf*ct-sf*dtheta)*(dtheta*rw+(dphi*sf*ct+cf*dtheta)*(rf+rt))))
    b3 = -2*dphi*st*Aw*dtheta-dtheta*Cw*(-dphi*st+dpsiw)+cf*(-Af*(dphi*sf*dpsif*ct+dphi*cf*st*dtheta+cf*dpsif*dtheta)-(dphi*sf*ct+cf*dtheta)*Cf*(-dphi*st+dpsif)+(-dphi*st+dpsif)*Bf*(dphi*sf*ct+cf*dtheta)+Ct*(-dphi*sf*dpsif*ct-dphi*cf*st*dtheta-cf*dpsif*dtheta))-sf*(-Bf*(dphi*cf*dpsif*ct-dphi*sf*st*dtheta-dpsif*sf*dtheta)-(-dphi*st+dpsif)*Af*(-dphi*cf*ct+sf*dtheta)+(-dphi*cf*ct+sf*dtheta)*Cf*(-dphi*st+dpsif)-At*(dphi*cf*dpsif*ct-dphi*sf*st*dtheta-dpsif*sf*dtheta)-(dphi*cf*ct-sf*dtheta)*At*(-dphi*st+dpsif)+(-dphi*st+dpsif)*Ct*(dphi*cf*ct-sf*dtheta+dpsit)+rf*(mf*g*st-mf*((dphi*sf*ct+cf*dtheta)*sf*(-dphi*st+dpsiw)*rw+(dphi*cf*dpsif*ct-dphi*sf*st*dtheta-dpsif*sf*dtheta)*rf+(-dphi*cf*ct+sf*dtheta)*(-cf*(-dphi*st+dpsiw)*rw-(-dphi*st+dpsif)*rf))+mt*g*st-mt*(-(dphi*cf*ct-sf*dtheta)*(-cf*(-dphi*st+dpsiw)*rw-(-dphi*st+dpsif)*(rf+rt))+(dphi*cf*dpsif*ct-dphi*sf*st*dtheta-dpsif*sf*dtheta)*(rf+rt)+(dphi*sf*ct+cf*dtheta)*sf*(-dphi*st+dpsiw)*rw))+rt*(mt*g*st-mt*(-(dphi*cf*ct-sf*dtheta)*(-cf*(-dphi*st+dpsiw)*rw-(-dphi*st+dpsif)*(rf+rt))+(dphi*cf*dpsif*ct-dphi*sf*st*dtheta-dpsif*sf*dtheta)*(rf+rt)+(dphi*sf*ct+cf*dtheta)*sf*(-dphi*st+dpsiw)*rw)))
    b4 = -dphi**2*st*Aw*ct-dphi*ct*Cw*(-dphi*st+dpsiw)-rw*(mw*dphi*ct*(-dphi*st+dpsiw)*rw-mt*g*st-mw*g*st+mf*((dphi*sf*ct+cf*dtheta)*sf*(-dphi*st+dpsiw)*rw+(dphi*cf*dpsif*ct-dphi*sf*st*dtheta-dpsif*sf*dtheta)*rf+(-dphi*cf*ct+sf*dtheta)*(-cf*(-dphi*st+dpsiw)*rw-(-dphi*st+dpsif)*rf))-mf*g*st+mt*(-(dphi*cf*ct-sf*dtheta)*(-cf*(-dphi*st+dpsiw)*rw-(-dphi*st+dpsif)*(rf+rt))+(dphi*cf*dpsif*ct-dphi*sf*st*dtheta-dpsif*sf*dtheta)*(rf+rt)+(dphi*sf*ct+cf*dtheta)*sf*(-dphi*st+dpsiw)*rw))+sf*(-Af*(dphi*sf*dpsif*ct+dphi*cf*st*dtheta+cf*dpsif*dtheta)-(dphi*sf*ct+cf*dtheta)*Cf*(-dphi*st+dpsif)+(-dphi*st+dpsif)*Bf*(dphi*sf*ct+cf*dtheta)+Ct*(-dphi*sf*dpsif*ct-dphi*cf*st*dtheta-cf*dpsif*dtheta))+cf*(-Bf*(dphi*cf*dpsif*ct-dphi*sf*st*dtheta-dpsif*sf*dtheta)-(-dphi*st+dpsif)*Af*(-dphi*cf*ct+sf*dtheta)+(-dphi*cf*ct+sf*dtheta)*Cf*(-dphi*st+dpsif)-At*(dphi*cf*dpsif*ct-dphi*sf*st*dtheta-dpsif*sf*dtheta)-(dphi*cf*ct-sf*dtheta)*At*(-dphi*st+dpsif)+(-dphi*st+dpsif)*Ct*(dphi*cf*ct-sf*dtheta+dpsit)+rf*(mf*g*st-mf*((dphi*sf*ct+cf*dtheta)*sf*(-dphi*st+dpsiw)*rw+(dphi*cf*dpsif*ct-dphi*sf*st*dtheta-dpsif*sf*dtheta)*rf+(-dphi*cf*ct+sf*dtheta)*(-cf*(-dphi*st+dpsiw)*rw-(-dphi*st+dpsif)*rf))+mt*g*st-mt*(-(dphi*cf*ct-sf*dtheta)*(-cf*(-dphi*st+dpsiw)*rw-(-dphi*st+dpsif)*(rf+rt))+(dphi*cf*dpsif*ct-dphi*sf*st*dtheta-dpsif*sf*dtheta)*(rf+rt)+(dphi*sf*ct+cf*dtheta)*sf*(-dphi*st+dpsiw)*rw))+rt*(mt*g*st-mt*(-(dphi*cf*ct-sf*dtheta)*(-cf*(-dphi*st+dpsiw)*rw-(-dphi*st+dpsif)*(rf+rt))+(dphi*cf*dpsif*ct-dphi*sf*st*dtheta-dpsif*sf*dtheta)*(rf+rt)+(dphi*sf*ct+cf*dtheta)*sf*(-dphi*st+dpsiw)*rw)))
    b5 = +2*Cw*dphi*ct*dtheta+(dphi*sf*ct+cf*dtheta)*Af*(-dphi*cf*ct+sf*dtheta)-rt*(-mt*g*sf*ct-mt*(sf*dpsif*(-dphi*st+dpsiw)*rw+cf*dphi*ct*dtheta*rw-(-dphi*st+dpsif)*sf*(-dphi*st+dpsiw)*rw+dphi*ct*dtheta*(rf+rt)+(dphi*cf*ct-sf*dtheta)*(dtheta*rw+(dphi*sf*ct+cf*dtheta)*(rf+rt))))-(dphi*sf*ct+cf*dtheta)*Ct*(dphi*cf*ct-sf*dtheta+dpsit)+At*dphi*ct*dtheta+rw*(2*mw*rw*dphi*ct*dtheta+sf*(mf*(-cf*dpsif*(-dphi*st+dpsiw)*rw+sf*dphi*ct*dtheta*rw+(dphi*sf*ct+cf*dtheta)*(dtheta*rw+(dphi*sf*ct+cf*dtheta)*rf)-(-dphi*st+dpsif)*(-cf*(-dphi*st+dpsiw)*rw-(-dphi*st+dpsif)*rf))-mf*g*cf*ct-mt*g*cf*ct-mt*(cf*dpsif*(-dphi*st+dpsiw)*rw-sf*dphi*ct*dtheta*rw+(-dphi*st+dpsif)*(-cf*(-dphi*st+dpsiw)*rw-(-dphi*st+dpsif)*(rf+rt))-(dphi*sf*ct+cf*dtheta)*(dtheta*rw+(dphi*sf*ct+cf*dtheta)*(rf+rt))))+cf*(mf*(sf*dpsif*(-dphi*st+dpsiw)*rw+cf*dphi*ct*dtheta*rw-(-dphi*cf*ct+sf*dtheta)*(dtheta*rw+(dphi*sf*ct+cf*dtheta)*rf)+dphi*ct*dtheta*rf-(-dphi*st+dpsif)*sf*(-dphi*st+dpsiw)*rw)+mt*g*sf*ct+mf*g*sf*ct+mt*(sf*dpsif*(-dphi*st+dpsiw)*rw+cf*dphi*ct*dtheta*rw-(-dphi*st+dpsif)*sf*(-dphi*st+dpsiw)*rw+dphi*ct*dtheta*(rf+rt)+(dphi*cf*ct-sf*dtheta)*(dtheta*rw+(dphi*sf*ct+cf*dtheta)*(rf+rt)))))+(dphi*cf*ct-sf*dtheta)*At*(dphi*sf*ct+cf*dtheta)-rf*(-mt*g*sf*ct-mt*(sf*dpsif*(-dphi*st+dpsiw)*rw+cf*dphi*ct*dtheta*rw-(-dphi*st+dpsif)*sf*(-dphi*st+dpsiw)*rw+dphi*ct*dtheta*(rf+rt)+(dphi*cf*ct-sf*dtheta)*(dtheta*rw+(dphi*sf*ct+cf*dtheta)*(rf+rt)))-mf*g*sf*ct-mf*(sf*dpsif*(-dphi*st+dpsiw)*rw+cf*dphi*ct*dtheta*rw-(-dphi*cf*ct+sf*dtheta)*(dtheta*rw+(dphi*sf*ct+cf*dtheta)*rf)+dphi*ct*dtheta*rf-(-dphi*st+dpsif)*sf*(-dphi*st+dpsiw)*rw))-(-dphi*cf*ct+sf*dtheta)*Bf*(dphi*sf*ct+cf*dtheta)

    A = jnp.stack([
        jnp.stack([a11, a12, a13, a14, a15]),
        jnp.stack([a21, a22, a23, a24, a25]),
        jnp.stack([a31, a32, a33, a34, a35]),
        jnp.stack([a41, a42, a43, a44, a45]),
        jnp.stack([a51, a52, a53, a54, a55]),
    ])
    b = jnp.stack([b1, b2, b3, b4, b5])
    return A, b


def _yaw_rotation(phi):
    """``R = -[[cos phi, sin phi], [-sin phi, cos phi]]``: contact point into the yawed frame."""
    c, s = jnp.cos(phi), jnp.sin(phi)
    return -jnp.array([[c, s], [-s, c]])


def _wheel_up_vector(theta, phi, dtheta, dphi):
    """The wheel plane's up vector ``n = Rz(phi) Rx(-theta) e_z`` and its time derivative."""
    st, ct, sp, cp = jnp.sin(theta), jnp.cos(theta), jnp.sin(phi), jnp.cos(phi)
    n = jnp.stack([-sp * st, cp * st, ct])
    n_dot = jnp.stack([-cp * st * dphi - sp * ct * dtheta, -sp * st * dphi + cp * ct * dtheta, -st * dtheta])
    return n, n_dot


@dataclasses.dataclass(frozen=True)
class Unicycle(Task):
    """Unicycle balancing. Options: preset, noise_k, dt, horizon, trial counts."""

    name: ClassVar[str] = "unicycle"
    state_names: ClassVar[tuple[str, ...]] = (
        "dtheta", "dphi", "dpsiw", "dpsif", "dpsit", "x", "y", "theta", "phi", "psiw", "psif", "psit")
    model_state_names: ClassVar[tuple[str, ...]] = (
        "dtheta", "dphi", "dpsiw", "dpsif", "dpsit", "xc", "yc", "theta", "phi", "psif")
    control_names: ClassVar[tuple[str, ...]] = ("V", "U")
    u_max: ClassVar[tuple[float, ...]] = (10.0, 50.0)
    mjcf: ClassVar[str] = os.path.join(os.path.dirname(__file__), "unicycle.xml")
    mjcf_label: ClassVar[str | None] = (
        "APPROXIMATE MuJoCo unicycle: a wheel in soft frictional contact with the floor, "
        "not the ideal rolling of the reference equations")
    value_slice_dims: ClassVar[tuple[str, str]] = ("theta", "psif")  # roll and pitch
    substep_dt: ClassVar[float] = 0.005  # 10 RK4 sub-steps per 0.1 s miss the reference by 5e-5; 20 by 3e-6
    presets: ClassVar[dict] = {
        "pipps": dict(dt=0.1, horizon=20, noise_k=1.0, num_random_trials=5, num_learned_trials=30),
        "pilco": dict(dt=0.15, horizon=67, noise_k=1.0, num_random_trials=10, num_learned_trials=40),
    }

    def derivative(self, z, u):
        """``[thetaddot, ..., psitddot] = -A^-1 b``; ``xdot = rw cos(phi) dpsiw``,
        ``ydot = rw sin(phi) dpsiw``; the angles' derivatives are the rates. (12,) -> (12,)."""
        check_vector("z (ODE state)", z, 12)
        check_vector("u (control)", u, 2)
        A, b = _equations_of_motion(z, u)
        accelerations = -solve_det(A, b[:, None])[0][:, 0]  # elementwise: vmap never batches LAPACK
        phi, dpsiw = z[8], z[2]
        contact_velocity = rw * dpsiw * jnp.stack([jnp.cos(phi), jnp.sin(phi)])
        return jnp.concatenate([accelerations, contact_velocity, z[:5]])

    def fallen(self, z):
        """The unicycle has fallen: ``|theta| > pi/2`` or ``|psif| > pi/2``."""
        return (jnp.abs(z[7]) > jnp.pi / 2) | (jnp.abs(z[10]) > jnp.pi / 2)

    def to_model_state(self, z):
        """``s = [rates, xc, yc, theta, phi, psif]``, ``[xc, yc] = R(phi) [x, y]``. (12,) -> (10,)."""
        check_vector("z (ODE state)", z, 12)
        contact = _yaw_rotation(z[8]) @ z[5:7]
        return jnp.concatenate([z[:5], contact, z[7:9], z[10:11]])

    def from_model_state(self, s):
        """An ODE state with modelled state s; the wheel and turntable angles (which the
        dynamics do not depend on) are set to 0. (10,) -> (12,)."""
        check_vector("s (modelled state)", s, 10)
        contact = _yaw_rotation(s[8]).T @ s[5:7]  # R is orthogonal: R^-1 = R^T
        zero = jnp.zeros((1,), s.dtype)
        return jnp.concatenate([s[:5], contact, s[7:9], zero, s[9:10], zero])

    def to_mujoco(self, z):
        """ODE state -> ``(qpos (8,), qvel (8,))`` of ``unicycle.xml`` (see its header).

        The axle centre is ``c = [x, y, 0] + rw n`` with the wheel plane's up vector
        ``n = Rz(phi) Rx(-theta) e_z = [-sin phi sin theta, cos phi sin theta, cos theta]``; rolling
        without slip gives ``cdot = rw dpsiw [cos phi, sin phi, 0] + rw ndot``."""
        check_vector("z (ODE state)", z, 12)
        dtheta, dphi, dpsiw, dpsif, dpsit = z[0], z[1], z[2], z[3], z[4]
        theta, phi, psiw, psif, psit = z[7], z[8], z[9], z[10], z[11]
        n, n_dot = _wheel_up_vector(theta, phi, dtheta, dphi)
        heading = jnp.stack([jnp.cos(phi), jnp.sin(phi), jnp.zeros_like(phi)])
        centre = jnp.concatenate([z[5:7], jnp.zeros((1,), z.dtype)]) + rw * n
        centre_dot = rw * dpsiw * heading + rw * n_dot
        qpos = jnp.concatenate([centre, jnp.stack([phi, theta, psif, psiw - psif, psit])])
        qvel = jnp.concatenate([centre_dot, jnp.stack([dphi, dtheta, dpsif, dpsiw - dpsif, dpsit])])
        return qpos, qvel

    def from_mujoco(self, qpos, qvel):
        """``(qpos (8,), qvel (8,))`` -> ODE state (12,); the contact point is ``c - rw n``
        (the lowest point of an ideal wheel; the slip and sinking of the contact are dropped)."""
        phi, theta, psif, psiw = qpos[3], qpos[4], qpos[5], qpos[5] + qpos[6]
        dphi, dtheta, dpsif, dpsiw = qvel[3], qvel[4], qvel[5], qvel[5] + qvel[6]
        n, _ = _wheel_up_vector(theta, phi, dtheta, dphi)
        contact = qpos[:2] - rw * n[:2]
        rates = jnp.stack([dtheta, dphi, dpsiw, dpsif, qvel[7]])
        angles = jnp.stack([theta, phi, psiw, psif, qpos[7]])
        return jnp.concatenate([rates, contact, angles])

    @property
    def cost_form(self) -> SaturatingCost:
        """``1 - exp(-1/2 (0.5 dx^2 + 0.5 dy^2 + 8 dz^2 + (phi / (4 pi))^2))`` with
        ``dx = xc - r_c sin(psif)``, ``dy = yc - (r_c + rw_c) sin(theta)``,
        ``dz = rw_c + r_c - rw_c cos(theta) - r_c cos(theta) cos(psif)``: the point
        ``[dx, dy, dz, phi]`` on the angles ``[psif, theta, theta + psif, theta - psif]``, with
        ``cos(theta) cos(psif) = (cos(theta + psif) + cos(theta - psif)) / 2``."""
        rwc, rc = COST_WHEEL_RADIUS, COST_FRAME_LENGTH
        angles = np.zeros((4, 10))
        angles[:, 7] = [0, 1, 1, 1]  # theta
        angles[:, 9] = [1, 0, 1, -1]  # psif
        # y = [s (10), sin/cos psif, sin/cos theta, sin/cos (theta + psif), sin/cos (theta - psif)]
        point = np.zeros((4, 18))
        point[0, [5, 10]] = [1, -rc]
        point[1, [6, 12]] = [1, -(rc + rwc)]
        point[2, [13, 15, 17]] = [-rwc, -rc / 2, -rc / 2]
        point[3, 8] = 1
        weight = np.diag([0.5, 0.5, 8.0, 1 / (4 * np.pi) ** 2])
        return SaturatingCost(TrigLinearMap.make(angles, point, [0.0, 0.0, rwc + rc, 0.0]),
                              tuple(map(tuple, weight.tolist())))

    @property
    def policy_feature_map(self) -> TrigLinearMap:
        """The whole modelled state."""
        return TrigLinearMap.select(10, angle_dims=(), keep=tuple(range(10)))

    @property
    def gp_feature_map(self) -> TrigLinearMap:
        """The modelled state without the yaw phi."""
        return TrigLinearMap.select(10, angle_dims=(), keep=(0, 1, 2, 3, 4, 5, 6, 7, 9))

    def cost(self, s):
        """Per-step cost of a modelled state (see ``cost_form``)."""
        check_vector("s (modelled state)", s, 10)
        return self.cost_form(s)

    def policy_features(self, s):
        """The policy sees the whole modelled state, (10,)."""
        check_vector("s (modelled state)", s, 10)
        return s

    def gp_features(self, s):
        """The GP sees the modelled state without the yaw phi, (9,)."""
        check_vector("s (modelled state)", s, 10)
        return jnp.concatenate([s[:8], s[9:]])

    @property
    def init_mean(self):
        return jnp.zeros(12)

    @property
    def init_std(self):
        """0.02 on the 5 rates, 0.1 on x and y, 0.02 on the 5 angles."""
        return jnp.array([0.02] * 5 + [0.1, 0.1] + [0.02] * 5)

    @property
    def model_initial_moments(self):
        """Exact moments of ``s_0 = to_model_state(z_0)``: the rates and angles keep theirs;
        ``[xc, yc] = R(phi) [x, y]`` is a rotation of a zero-mean isotropic (x, y) independent of
        phi, so it has mean 0, covariance sigma_xy^2 I, and no correlation with anything."""
        mean, std = np.asarray(self.init_mean, float), np.asarray(self.init_std, float)
        if mean[5] != 0 or mean[6] != 0 or std[5] != std[6]:
            raise ValueError("model_initial_moments assumes x and y with mean 0 and equal std")
        keep = [0, 1, 2, 3, 4, 5, 6, 7, 8, 10]  # the ODE entries behind s (x, y stand for xc, yc)
        return mean[keep], np.diag(std[keep] ** 2)

    @property
    def obs_noise_std(self):
        """sqrt(k) * (0.01 on the 5 rates, 0.003 on the other 7)."""
        return jnp.sqrt(self.noise_k) * jnp.array([0.01] * 5 + [0.003] * 7)

    def default_policy(self) -> Policy:
        """Linear policy on the modelled state, ``u = [10, 50] * sat(W s + b)``."""
        return linear_policy(self.model_state_dim, self.u_max)
