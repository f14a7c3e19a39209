"""Batched rigid-body dynamics of planar serial chains (fixed base or on a cart).

One model covers the acrobot, the pendulum and the (double) cart-pole. Joint
coordinates are q = [x_cart?, th_1 .. th_N] with th_1 absolute (plus a constant
``angle_offset``) and th_k relative to the previous link; velocities v = dq/dt.
Absolute link angles phi_k = offset + th_1 + ... + th_k are measured from hanging
down, counter-clockwise, so the centre of mass of link i sits at

    p_i = [x + sum_{j<i} l_j sin phi_j + lc_i sin phi_i,  -sum_{j<i} l_j cos phi_j - lc_i cos phi_i].

The Lagrangian in (x, phi) gives, with a_j = m_j lc_j + l_j sum_{i>j} m_i and
C_jk = l_min(j,k) a_max(j,k) (C_jj = I_j + m_j lc_j^2 + l_j^2 sum_{i>j} m_i):

    x row:   M_tot xdd + sum_j a_j (cos phi_j phidd_j - sin phi_j phid_j^2) = F
    phi_j:   a_j cos phi_j xdd + sum_k C_jk cos(phi_j - phi_k) phidd_k
             + sum_k C_jk sin(phi_j - phi_k) phid_k^2 + g a_j sin phi_j = Q_j

and J = d(x, phi)/d(q) maps it to joint coordinates: J^T (M_abs J qdd + b_abs) = B u - D v.

The functions below take an array namespace (numpy or torch) so the Drake
controller blocks (numpy, one state) and the training fast path (torch, batched,
differentiable) share one formula.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass(frozen=True)
class ChainParams:
    """Physical constants of a planar chain, derived once from a spec's params."""

    has_cart: bool
    cart_mass: float
    link_mass: np.ndarray
    link_length: np.ndarray
    link_com: np.ndarray
    link_inertia: np.ndarray
    joint_damping: np.ndarray
    gravity: float
    angle_offset: float
    actuation: np.ndarray  # (n_q, n_u) selection matrix B

    @property
    def n_links(self) -> int:
        """Number of pendulum links."""
        return len(self.link_mass)

    @property
    def n_q(self) -> int:
        """Number of joint coordinates (cart + links)."""
        return self.n_links + int(self.has_cart)

    def first_moments(self) -> np.ndarray:
        """a_j = m_j lc_j + l_j * (mass of all links beyond j)."""
        m, l, lc = self.link_mass, self.link_length, self.link_com
        beyond = np.array([m[j + 1:].sum() for j in range(self.n_links)])
        return m * lc + l * beyond

    def coupling(self) -> np.ndarray:
        """Constant part C_jk of the link inertia matrix H_jk = C_jk cos(phi_j - phi_k)."""
        m, l, lc, inertia = self.link_mass, self.link_length, self.link_com, self.link_inertia
        a = self.first_moments()
        n = self.n_links
        C = np.zeros((n, n))
        for j in range(n):
            C[j, j] = inertia[j] + m[j] * lc[j] ** 2 + l[j] ** 2 * m[j + 1:].sum()
            for k in range(j + 1, n):
                C[j, k] = C[k, j] = l[j] * a[k]
        return C

    def jacobian(self) -> np.ndarray:
        """J mapping joint velocities to (x, phi) velocities: cumulative sums of joint angles."""
        n_q, c = self.n_q, int(self.has_cart)
        J = np.zeros((n_q, n_q))
        if self.has_cart:
            J[0, 0] = 1.0
        J[c:, c:] = np.tril(np.ones((self.n_links, self.n_links)))
        return J


class _Namespace:
    """The few array operations the chain formula needs, for numpy or torch."""

    def __init__(self, like):
        self.torch = isinstance(like, torch.Tensor)

    def const(self, array: np.ndarray, like):
        if self.torch:
            return torch.as_tensor(array, dtype=like.dtype, device=like.device)
        return np.asarray(array, dtype=like.dtype if like.dtype.kind == "f" else float)

    def cat(self, parts, axis):
        return torch.cat(parts, dim=axis) if self.torch else np.concatenate(parts, axis=axis)

    def cumsum(self, a):
        return torch.cumsum(a, dim=-1) if self.torch else np.cumsum(a, axis=-1)

    def solve(self, A, b):
        if self.torch:
            return torch.linalg.solve(A, b.unsqueeze(-1)).squeeze(-1)
        return np.linalg.solve(A, b[..., None])[..., 0]

    def cos(self, a):
        return torch.cos(a) if self.torch else np.cos(a)

    def sin(self, a):
        return torch.sin(a) if self.torch else np.sin(a)


class ChainDynamics:
    """Manipulator terms and time derivatives of a planar chain, for numpy or torch arrays."""

    def __init__(self, params: ChainParams):
        self.p = params
        self._a = params.first_moments()
        self._C = params.coupling()
        self._J = params.jacobian()
        self._total_mass = params.cart_mass + params.link_mass.sum() if params.has_cart else 0.0
        self._cache: dict = {}

    def _consts(self, like):
        """Constants as arrays of ``like``'s type, dtype and device (cached for torch)."""
        key = (type(like), str(getattr(like, "dtype", "")), str(getattr(like, "device", "")))
        if key not in self._cache:
            xp = _Namespace(like)
            self._cache[key] = (xp, xp.const(self._a, like), xp.const(self._C, like),
                                xp.const(self._J, like), xp.const(self.p.actuation, like),
                                xp.const(self.p.joint_damping, like))
        return self._cache[key]

    def absolute_angles(self, q):
        """Link angles phi_k from hanging down (..., N) and the base position (..., 1) or None."""
        xp = self._consts(q)[0]
        c = int(self.p.has_cart)
        phi = xp.cumsum(q[..., c:]) + self.p.angle_offset
        return phi, (q[..., :1] if self.p.has_cart else None)

    def manipulator(self, q, v):
        """Mass matrix M(q) (..., n_q, n_q) and bias b(q, v) (..., n_q) in joint coordinates.

        The equations of motion are M qdd + b = B u, with damping included in b.
        """
        xp, a, C, J, _, damping = self._consts(q)
        c = int(self.p.has_cart)
        phi = xp.cumsum(q[..., c:]) + self.p.angle_offset
        phid = xp.cumsum(v[..., c:])
        dphi = phi[..., :, None] - phi[..., None, :]
        H = C * xp.cos(dphi)
        link_bias = ((C * xp.sin(dphi)) @ (phid * phid)[..., None])[..., 0] + self.p.gravity * a * xp.sin(phi)
        if self.p.has_cart:
            coupling = a * xp.cos(phi)                                     # (..., N)
            top = xp.cat([q[..., :1] * 0 + self._total_mass, coupling], axis=-1)[..., None, :]
            rest = xp.cat([coupling[..., :, None], H], axis=-1)
            M_abs = xp.cat([top, rest], axis=-2)
            cart_bias = -(a * xp.sin(phi) * phid * phid).sum(-1)[..., None]
            b_abs = xp.cat([cart_bias, link_bias], axis=-1)
        else:
            M_abs, b_abs = H, link_bias
        JT = J.T if not xp.torch else J.transpose(0, 1)
        M = JT @ M_abs @ J
        b = (JT @ b_abs[..., None])[..., 0] + damping * v
        return M, b

    def accelerations(self, q, v, u):
        """qdd = M^-1 (B u - b)."""
        B = self._consts(q)[4]
        M, b = self.manipulator(q, v)
        xp = self._consts(q)[0]
        return xp.solve(M, (B @ u[..., None])[..., 0] - b)

    def derivatives(self, x, u):
        """Time derivative [v, qdd] of x = [q, v] under input u (batched over leading dims)."""
        n_q = self.p.n_q
        q, v = x[..., :n_q], x[..., n_q:]
        qdd = self.accelerations(q, v, u)
        xp = self._consts(x)[0]
        return xp.cat([v, qdd], axis=-1)

    def energy(self, x):
        """Total mechanical energy (kinetic + potential, zero potential at the pivot height)."""
        n_q = self.p.n_q
        q, v = x[..., :n_q], x[..., n_q:]
        M, _ = self.manipulator(q, v * 0)
        kinetic = 0.5 * (v[..., None, :] @ M @ v[..., :, None])[..., 0, 0]
        phi, _ = self.absolute_angles(q)
        xp, a = self._consts(x)[:2]
        potential = -self.p.gravity * (a * xp.cos(phi)).sum(-1)
        return kinetic + potential

    def tip_height(self, x):
        """Height of the distal tip above the base pivot: -sum_j l_j cos phi_j."""
        phi, _ = self.absolute_angles(x[..., :self.p.n_q])
        xp = self._consts(x)[0]
        l = xp.const(self.p.link_length, x)
        return -(l * xp.cos(phi)).sum(-1)
