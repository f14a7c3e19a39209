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

Folded form (what is evaluated). Every q-dependent factor above is the sine or
cosine of one of a few "angle features": the absolute angles phi_j and the
relative angles r_jk = phi_k - phi_j = th_{j+1} + ... + th_k (j < k), so that
cos(phi_j - phi_k) = cos r_jk and sin(phi_j - phi_k) = -sin r_jk. Since J is
constant, J^T (...) J can be multiplied out once, in ``__init__``:

    M(q)_ik = M0_ik + sum_f KM_fik cos(angle_f)
    b(q, v)_i = sum_f G_fi sin(angle_f) + sum_{f,k} W_fki sin(angle_f) phid_k^2 + D_i v_i

with constant tables M0 = J^T Mabs0 J, KM_f = J^T Kabs_f J, G_f = J^T Gabs_f and
W_fk = J^T Wabs_fk built from the formulas above (see ``_fold``). Only the
nonzero coefficients are kept, so each entry costs a handful of elementwise
operations on (batch,) columns, and M is inverted in closed form for n_q <= 3
(Cramer's rule on the symmetric 1x1, 2x2, 3x3 matrix) instead of a batched LU.

The functions below take an array namespace (numpy or torch; :mod:`hybridctl.systems.array_namespace`)
so the Drake controller blocks (numpy, one state: evaluated on Python floats) and the
training fast path (torch, batched, differentiable) share one formula. A third
"namespace", ``_CodeWriter`` (:mod:`hybridctl.systems.generated_code`), runs the same formula on
symbols and records it as straight-line Python over floats (``ChainDynamics.scalar``): one state then costs a few
microseconds per step instead of tens of torch calls (``System.step`` on one float64
state, ``System.step_single``, ``SwingupEnv``). ``_TorchCodeWriter`` records the torch
namespace's calls the same way (``ChainDynamics.torch_step``, what ``System.step`` runs on
batches): bit for bit the table-driven result, without its Python bookkeeping per call.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from .array_namespace import NUMPY_NAMESPACE, ArrayNamespace, solve_symmetric
from .generated_code import scalar_source, shared_function, torch_source


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



class ChainDynamics:
    """Manipulator terms and time derivatives of a planar chain, for numpy or torch arrays."""

    def __init__(self, params: ChainParams):
        self.p = params
        self._a = params.first_moments()
        self._C = params.coupling()
        self._J = params.jacobian()
        self._total_mass = params.cart_mass + params.link_mass.sum() if params.has_cart else 0.0
        self._fold()
        self._namespaces: dict = {}
        self._scalar: dict = {}
        self._torch_code: dict = {}
        self._lengths = [float(v) for v in params.link_length]

    def _xp(self, like) -> ArrayNamespace:
        """The namespace for ``like`` (one per torch dtype and device, so constants are cached)."""
        if not isinstance(like, torch.Tensor):
            return NUMPY_NAMESPACE
        key = (like.dtype, like.device)
        xp = self._namespaces.get(key)
        if xp is None:
            xp = self._namespaces[key] = ArrayNamespace(like)
        return xp

    def scalar(self, dt: float | None = None, integrator: str | None = None, bound: float | None = None):
        """A compiled one-state function over plain Python floats (cached per arguments).

        ``scalar()`` is ``f(x, u) -> list``, dx/dt at one state; ``scalar(dt, integrator,
        bound)`` is ``f(x, u, steps) -> list | None``, ``steps`` steps of the integrator
        (``euler`` or ``runge_kutta2``), None once a coordinate leaves [-bound, bound] or is
        NaN (``bound`` None: no check). ``x`` and ``u`` are sequences of floats.

        The function is the numpy path's formula written out as straight-line code
        (:class:`_CodeWriter`): it agrees with the batched torch path to rounding (~1e-14
        relative; torch fuses multiply-adds) at a few microseconds per step. It calls
        ``math.sin``, so a non-finite angle raises ValueError; callers fall back to torch.
        Chains with more than 3 joint coordinates raise NotImplementedError.
        """
        key = (dt, integrator, bound)
        fn = self._scalar.get(key)
        if fn is None:
            source = scalar_source(self, "scalar_step", dt, integrator, bound) if integrator is not None \
                else scalar_source(self, "scalar_derivatives", 0.0, None, None)
            fn = self._scalar[key] = shared_function(
                source, "scalar_step" if integrator is not None else "scalar_derivatives",
                {"_sin": math.sin, "_cos": math.cos}, f"<hybridctl.systems.dynamics scalar {key}>")
        return fn

    def generate_torch_step(self, dt: float, integrator: str | None):
        """The generated straight-line torch step for (``dt``, ``integrator``), cached; None for chains
        the generator does not cover (they use the table-driven path)."""
        key = (dt, integrator)
        if key not in self._torch_code:
            try:
                source, constants = torch_source(self, dt, integrator)
            except NotImplementedError:
                fn = None
            else:
                fn = shared_function(source, "torch_step", {"_torch": torch},
                                     f"<hybridctl.systems.dynamics torch {key}>", constants)
            self._torch_code[key] = fn
        return self._torch_code[key]

    def torch_step_columns(self, x, u, dt: float, integrator: str, compiled: bool = False):
        """One integrator step of states stored column-major: ``x`` (n, batch), ``u`` (m, batch),
        each row contiguous over the batch; returns (n, batch). The formula and operations of
        :meth:`torch_step` (the same numbers, bit for bit, eager), on data laid out so that
        every operation reads contiguous memory. ``compiled``: through ``torch.compile`` (built
        on first use per dtype/shape, ~15 s; inductor fuses the step into one vectorised loop,
        which it cannot do on interleaved (batch, n) rows; agrees with eager to rounding).
        Differentiable eager; chains of more than 3 joint coordinates are not supported."""
        if self.p.n_q > 3:
            raise NotImplementedError("column-major steps need the closed-form solve (<= 3 joint coordinates)")
        key = ("columns", dt, integrator)
        fn = self._torch_code.get(key)
        if fn is None:
            source, constants = torch_source(self, dt, integrator, columns=True)
            fn = self._torch_code[key] = shared_function(source, "torch_step", {"_torch": torch},
                                                         f"<hybridctl.systems.dynamics torch {key}>", constants)
        xp = self._xp(x)
        if compiled:
            fast = self._torch_code.get(("compiled",) + key)
            if fast is None:
                fast = self._torch_code[("compiled",) + key] = torch.compile(fn, dynamic=False)
            fn = fast
        return fn(x, u, None, xp.consts_for(self._torch_code[key]))

    def torch_step(self, x, u, dt: float | None = None, integrator: str | None = None):
        """The batched torch derivatives (``integrator`` None) or one step of ``integrator`` with
        ``dt`` (``euler``: x + dt f; ``runge_kutta2``: x + (0.5 dt)(k1 + k2), k2 at x + dt k1),
        through generated straight-line torch code (:class:`_TorchCodeWriter`): the same torch
        calls as the table-driven path, bit for bit, with less Python per call. Differentiable.
        Chains of more than 3 joint coordinates use the table-driven path."""
        xp = self._xp(x)
        key = (dt, integrator)
        fn = self._torch_code.get(key)
        # generating code (exec) inside a torch.compile trace would break the graph: there the
        # table-driven path below runs (the same torch calls); System generates its own step up front
        if fn is None and key not in self._torch_code and not torch.compiler.is_compiling():
            fn = self.generate_torch_step(dt, integrator)
        if fn is None:
            k1 = self.derivatives(x, u)
            if integrator is None:
                return k1
            if integrator == "euler":
                return x + dt * k1
            return x + 0.5 * dt * (k1 + self.derivatives(x + dt * k1, u))
        K = xp.consts_for(fn)
        return fn(x, u, xp, K)

    def _fold(self) -> None:
        """Tables of the folded form (module docstring), kept as lists of nonzero terms.

        Terms are (coef, key) or (coef, key1, key2) over the keys ("sin", f),
        ("cos", f), ("phid2", k) = phid_k^2, ("v", i), ("u", col) that
        ``_columns`` evaluates; feature f < N is phi_f, feature N + p is r_jk of
        the p-th pair (j, k) in ``self._pairs``.
        """
        p, a, C, J = self.p, self._a, self._C, self._J
        N, n_q, c = p.n_links, p.n_q, int(p.has_cart)
        self._pairs = [(j, k) for j in range(N) for k in range(j + 1, N)]
        n_f = N + len(self._pairs)
        # In absolute coordinates (x, phi): M_abs = Mabs0 + sum_f Kabs_f cos(angle_f) and
        # b_abs = sum_f Gabs_f sin(angle_f) + sum_{f,k} Wabs_fk sin(angle_f) phid_k^2.
        Mabs0, Kabs = np.zeros((n_q, n_q)), np.zeros((n_f, n_q, n_q))
        Gabs, Wabs = np.zeros((n_f, n_q)), np.zeros((n_f, N, n_q))
        if p.has_cart:
            Mabs0[0, 0] = self._total_mass
        for j in range(N):
            Mabs0[c + j, c + j] = C[j, j]
            Gabs[j, c + j] = p.gravity * a[j]                  # g a_j sin phi_j
            if p.has_cart:
                Kabs[j, 0, c + j] = Kabs[j, c + j, 0] = a[j]   # a_j cos phi_j (x-phi_j coupling)
                Wabs[j, j, 0] = -a[j]                          # x row: -a_j sin phi_j phid_j^2
        for f, (j, k) in enumerate(self._pairs, start=N):
            Kabs[f, c + j, c + k] = Kabs[f, c + k, c + j] = C[j, k]   # C_jk cos(phi_j - phi_k)
            Wabs[f, k, c + j] = -C[j, k]   # row j: C_jk sin(phi_j - phi_k) phid_k^2 = -C_jk sin r_jk phid_k^2
            Wabs[f, j, c + k] = C[j, k]    # row k: C_kj sin(phi_k - phi_j) phid_j^2 = +C_jk sin r_jk phid_j^2
        # Fold in the constant J: M = J^T M_abs J and b = J^T b_abs + D v.
        M0 = J.T @ Mabs0 @ J
        KM = np.einsum("ai,fab,bk->fik", J, Kabs, J)
        G, W = Gabs @ J, Wabs @ J
        # Upper triangle of M: {(i, k): (constant, [(coef, ("cos", f))])}.
        self._M_entries = {(i, k): (float(M0[i, k]), [(float(KM[f, i, k]), ("cos", f))
                                                      for f in range(n_f) if KM[f, i, k] != 0.0])
                           for i in range(n_q) for k in range(i, n_q)}
        self._bias_rows = []
        for i in range(n_q):
            row = [(float(G[f, i]), ("sin", f)) for f in range(n_f) if G[f, i] != 0.0]
            row += [(float(W[f, k, i]), ("sin", f), ("phid2", k))
                    for f in range(n_f) for k in range(N) if W[f, k, i] != 0.0]
            if p.joint_damping[i] != 0.0:
                row.append((float(p.joint_damping[i]), ("v", i)))
            self._bias_rows.append(row)
        # Right-hand sides of M qdd = B u - b, what the solve needs.
        self._rhs_rows = [[(float(p.actuation[i, col]), ("u", col)) for col in range(p.actuation.shape[1])
                           if p.actuation[i, col] != 0.0] + [(-t[0],) + t[1:] for t in self._bias_rows[i]]
                          for i in range(n_q)]
        # What _columns must evaluate: only the trig functions and velocities some term uses.
        keys = {key for _, terms in self._M_entries.values() for _, key in terms}
        keys |= {key for row in self._rhs_rows for term in row for key in term[1:]}
        self._sin = [f for f in range(n_f) if ("sin", f) in keys]
        self._cos = [f for f in range(n_f) if ("cos", f) in keys]
        self._phid2 = [k for k in range(N) if ("phid2", k) in keys]

    def _columns(self, xp, q, v, u=()):
        """Every quantity the tables refer to, by key, from columns of q, v (and u)."""
        p, c, N = self.p, int(self.p.has_cart), self.p.n_links
        th = q[c:]
        # phi_1 = th_1 + offset, phi_j = phi_{j-1} + th_j (the order of Drake's AcrobotPlant: sin(q1 + q2)).
        angles = [xp.lincomb(p.angle_offset, [(1.0, th[0])])]
        for j in range(1, N):
            angles.append(angles[-1] + th[j])
        # r_jk = th_{j+1} + ... + th_k, summed directly (not phi_k - phi_j, which would cancel).
        rel = {}
        for j, k in self._pairs:
            rel[j, k] = th[k] if k == j + 1 else rel[j, k - 1] + th[k]
            angles.append(rel[j, k])
        cols = {("v", i): vi for i, vi in enumerate(v)}
        cols.update((("u", i), ui) for i, ui in enumerate(u))
        for f in self._sin:
            cols["sin", f] = xp.sin(angles[f])
        for f in self._cos:
            cols["cos", f] = xp.cos(angles[f])
        phid = None
        for k in range(max(self._phid2, default=-1) + 1):
            phid = v[c] if k == 0 else phid + v[c + k]     # phid_k = v_1 + ... + v_k
            if k in self._phid2:
                cols["phid2", k] = phid * phid
        return cols

    @staticmethod
    def _evaluate(xp, const, terms, cols):
        """One table entry (const + terms) at the evaluated columns."""
        return xp.lincomb(const, [(t[0], cols[t[1]]) if len(t) == 2 else (t[0], cols[t[1]], cols[t[2]])
                                  for t in terms])

    def _mass_entries(self, xp, cols):
        """Upper triangle {(i, k): column or float} of M."""
        return {ik: self._evaluate(xp, const, terms, cols) for ik, (const, terms) in self._M_entries.items()}

    def _matrix(self, xp, m, like):
        """The symmetric (..., n_q, n_q) matrix from its upper triangle."""
        n_q = self.p.n_q
        flat = xp.stack([m[min(i, k), max(i, k)] for i in range(n_q) for k in range(n_q)], like)
        return flat.reshape(flat.shape[:-1] + (n_q, n_q))

    def _accelerations(self, xp, q, v, u):
        """qdd as a list of columns, from columns of q, v and u."""
        n_q = self.p.n_q
        cols = self._columns(xp, q, v, u)
        m = self._mass_entries(xp, cols)
        r = [self._evaluate(xp, 0.0, row, cols) for row in self._rhs_rows]
        if n_q <= 3:
            return solve_symmetric(xp, [[m.get((i, k)) for k in range(n_q)] for i in range(n_q)], r)
        # Longer chains: a batched LU solve of the assembled matrix.
        return xp.columns(xp.solve(self._matrix(xp, m, q[0]), xp.stack(r, q[0])))

    # ------------------------------------------------------------------ public
    def absolute_angles(self, q):
        """Link angles phi_k from hanging down (..., N) and the base position (..., 1) or None."""
        xp = self._xp(q)
        c = int(self.p.has_cart)
        phi = xp.cumsum(q[..., c:]) + self.p.angle_offset
        return phi, (q[..., :1] if self.p.has_cart else None)

    def manipulator(self, q, v):
        """Mass matrix M(q) (..., n_q, n_q) and bias b(q, v) (..., n_q) in joint coordinates.

        The equations of motion are M qdd + b = B u, with damping included in b.
        """
        xp = self._xp(q)
        qc, vc = xp.columns(q), xp.columns(v)
        cols = self._columns(xp, qc, vc)
        b = [self._evaluate(xp, 0.0, row, cols) for row in self._bias_rows]
        return self._matrix(xp, self._mass_entries(xp, cols), qc[0]), xp.stack(b, qc[0])

    def accelerations(self, q, v, u):
        """qdd = M^-1 (B u - b)."""
        xp = self._xp(q)
        qc = xp.columns(q)
        return xp.stack(self._accelerations(xp, qc, xp.columns(v), xp.columns(u)), qc[0])

    def derivatives(self, x, u):
        """Time derivative [v, qdd] of x = [q, v] under input u (batched over leading dims)."""
        xp = self._xp(x)
        if xp.torch and self.p.n_q <= 3:
            return self.torch_step(x, u)          # the same calls, generated once
        cols = xp.columns(x)
        q, v = cols[:self.p.n_q], cols[self.p.n_q:]
        return xp.stack(v + self._accelerations(xp, q, v, xp.columns(u)), cols[0])

    def energy(self, x):
        """Total mechanical energy (kinetic + potential, zero potential at the pivot height)."""
        n_q = self.p.n_q
        q, v = x[..., :n_q], x[..., n_q:]
        M, _ = self.manipulator(q, v * 0)
        kinetic = 0.5 * (v[..., None, :] @ M @ v[..., :, None])[..., 0, 0]
        phi, _ = self.absolute_angles(q)
        xp = self._xp(x)
        a = torch.as_tensor(self._a, dtype=x.dtype, device=x.device) if xp.torch else self._a
        potential = -self.p.gravity * (a * xp.cos(phi)).sum(-1)
        return kinetic + potential

    def tip_position(self, x):
        """(horizontal, height) of the distal tip: base x + sum_j l_j sin phi_j, -sum_j l_j cos phi_j
        (height above the base pivot)."""
        phi, base = self.absolute_angles(x[..., :self.p.n_q])
        xp = self._xp(x)
        l = self.p.link_length
        l = torch.as_tensor(l, dtype=x.dtype, device=x.device) if xp.torch else l
        horizontal = (l * xp.sin(phi)).sum(-1) + (base[..., 0] if base is not None else 0.0)
        return horizontal, -(l * xp.cos(phi)).sum(-1)

    def tip_height_single(self, x) -> float:
        """:meth:`tip_height` of one state given as a sequence of floats (plain float arithmetic,
        the operations of the array path in its order)."""
        c, offset = int(self.p.has_cart), self.p.angle_offset
        cumulative, height = 0.0, None
        for length, th in zip(self._lengths, x[c:c + self.p.n_links]):
            cumulative = cumulative + th
            term = length * math.cos(cumulative + offset)
            height = term if height is None else height + term
        return -height

    def tip_height(self, x):
        """Height of the distal tip above the base pivot: -sum_j l_j cos phi_j."""
        return self.tip_position(x)[1]
