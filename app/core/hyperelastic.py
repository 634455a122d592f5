"""Large deformation with a compressible neo-Hookean law (the ``hyperelastic`` effect).

Strain energy per reference volume (Bonet & Wood, eq. 6.27)

    W(F) = mu / 2 (tr C - 3) - mu ln J + lam / 2 (ln J)^2,    C = F^T F, J = det F

with the Lame parameters of each region's Young's modulus and the model's
Poisson's ratio, so that for small strains it is the linear model exactly. The
first Piola-Kirchhoff stress is P = mu (F - F^-T) + lam ln J F^-T.

The probe travel is applied in load steps. At each step the equilibrium
R(u) = f_int(u) = 0 on the free dofs is solved by a modified Newton iteration
whose fixed matrix is a factorized tangent, accelerated by Anderson mixing,
with a backtracking line search on the stored energy. A tangent is refactorized
only where the iteration is slow, and only a positive definite one is used
(its Cholesky factorization fails otherwise): off the equilibrium path, e.g. at a predicted state
beside the probe's edges, the tangent can have negative eigenvalues, its step
need not lower the energy, and iterating with it stalled the walk (on the demo
phantom at 12.5 of 14.8 mm, with steps of 0.03 mm failing, although the
equilibria there have a positive definite tangent). Such a tangent is shifted
towards its diagonal (a Levenberg-Marquardt step) until it is positive definite.
The first solve walks
the load path (continuation from step to step); it leaves, at every requested
travel, the equilibrium and the tangent factorized there (positive definite at
a stable equilibrium). A later solve with moduli ratios near those starts each
travel from that equilibrium with that tangent, so inside a fit a solve costs a
few iterations per travel and no factorization. The reaction on the probe is
the probe's share of f_int.

The energy is integrated with the linear model's 4-point rule, except in the
tets beside the probe face's outline, where the deformation is largest: there
an 8-point rule (exact for cubics) keeps elements from deforming in ways four
points do not see (see :func:`edge_elements`). Both rules are exact for the
small-strain stiffness, so the linear limit is the linear model's.

Like the linear field, the hyperelastic field under displacement control
depends only on the ratios of the moduli, and the force scales with their level.

Units: mm, kPa, N (f_int is in mN with kPa and mm).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import scipy.sparse as sp

from app.core import memory
from app.core.errors import Cancelled, ElastoidError
from app.core.fem import QUAD_BARY, QUAD_W, coefficients, element_positions, lame, shape_gradients
from app.core.forward import MN_TO_N, FEModel
from app.core.solver import SymmetricFactor, single_threaded_blas


# ---------------------------------------------------------------------------
# the material law, on deformation gradients stored by component (9, n)
# ---------------------------------------------------------------------------


def _by_component(F: np.ndarray) -> np.ndarray:
    """(..., 3, 3) matrices stored by component: (9, n), F_00, F_01, ..., F_22."""
    return np.ascontiguousarray(np.asarray(F, float).reshape(-1, 9).T)


def _cofactors(Fc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """det F (n,) and the cofactor matrix J F^-T (9, n) of matrices stored by
    component (see :func:`_law`)."""
    a, b, c, d, e, f, g, h, i = Fc
    cof = np.empty_like(Fc)
    for k, (x1, y1, x2, y2) in enumerate(((e, i, f, h), (f, g, d, i), (d, h, e, g), (c, h, b, i), (a, i, c, g),
                                          (b, g, a, h), (b, f, c, e), (c, d, a, f), (a, e, b, d))):
        np.multiply(x1, y1, out=cof[k])
        cof[k] -= x2 * y2
    J = a * cof[0]
    J += b * cof[1]
    J += c * cof[2]
    return J, cof


def _law(Fc: np.ndarray, mu, lam, weights=None):
    """The law on deformation gradients stored by component: ``Fc`` (9, n) holds
    F_00, F_01, ..., F_22 (row-major), each a contiguous row, so every operation
    runs over long arrays (about 4x faster than on (n, 3, 3) stacks at paper
    size). Returns (P (9, n), W (n,)), P times ``weights`` when given (the
    quadrature weights, so that the internal force is one product with the
    gradient operator's transpose)."""
    J, cof = _cofactors(Fc)  # cof = J F^-T by component
    if not np.all(J > 0):
        raise ValueError("inverted element (det F <= 0)")
    lnJ = np.log(J)
    mu = np.asarray(mu, float)
    lam = np.asarray(lam, float)
    W = np.einsum("kn,kn->n", Fc, Fc)
    W -= 3.0
    W *= 0.5 * mu
    W += lnJ * (0.5 * lam * lnJ - mu)
    # P = mu F + (lam ln J - mu) F^-T,  F^-T = cof / J
    s = (lam * lnJ - mu) / J
    wmu = mu if weights is None else weights * mu
    if weights is not None:
        s *= weights
    P = Fc * wmu
    cof *= s
    P += cof
    return P, W


def neo_hookean_stress(F: np.ndarray, mu, lam) -> np.ndarray:
    """First Piola-Kirchhoff stress P (..., 3, 3) in kPa; mu, lam broadcast over F's leading axes."""
    F = np.asarray(F, float)
    lead = F.shape[:-2]
    P, _ = _law(_by_component(F), np.broadcast_to(mu, lead).ravel(), np.broadcast_to(lam, lead).ravel())
    return P.T.reshape(F.shape)


def neo_hookean_energy(F: np.ndarray, mu, lam) -> np.ndarray:
    """Strain energy density W (...) in kPa."""
    F = np.asarray(F, float)
    lead = F.shape[:-2]
    _, W = _law(_by_component(F), np.broadcast_to(mu, lead).ravel(), np.broadcast_to(lam, lead).ravel())
    return W.reshape(lead)


def uniaxial_stress_kPa(stretch: float, youngs_kPa: float, nu: float) -> tuple[float, float]:
    """Closed form of uniaxial loading of the neo-Hookean block: F = diag(a, a, s)
    with free lateral faces. Returns (nominal stress P_33 kPa, lateral stretch a),
    a from the scalar equation P_11(a) = mu (a - 1/a) + lam ln(a^2 s) / a = 0."""
    from scipy.optimize import brentq

    mu, lam = lame(youngs_kPa, nu)
    s = float(stretch)

    def p11(a):
        return mu * (a - 1.0 / a) + lam * np.log(a * a * s) / a

    a = brentq(p11, 1e-3, 1e3, xtol=1e-15, rtol=1e-15)
    return mu * (s - 1.0 / s) + lam * np.log(a * a * s) / s, a


# ---------------------------------------------------------------------------
# the discrete problem
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class HyperelasticSolution:
    """Equilibria along the load path: one per probe travel in ``depths_mm``."""

    depths_mm: np.ndarray  # (k,)
    force_N: np.ndarray  # (k,) reaction on the probe (compression positive)
    fields: np.ndarray  # (k, n_dofs) displacement mm
    iterations: tuple  # per load step

    def force_curve_N(self, displacement_mm) -> np.ndarray:
        """Force at any travel, by monotone cubic interpolation of the solved steps
        (zero travel -> zero force)."""
        from scipy.interpolate import PchipInterpolator

        d = np.concatenate([[0.0], self.depths_mm])
        F = np.concatenate([[0.0], self.force_N])
        x = np.clip(np.asarray(displacement_mm, float), 0.0, None)
        inside = np.clip(x, 0.0, d[-1])
        out = PchipInterpolator(d, F, extrapolate=True)(inside)
        # beyond the last step: continue with the last secant stiffness
        k_end = (F[-1] - F[-2]) / (d[-1] - d[-2])
        return np.where(x > d[-1], F[-1] + k_end * (x - d[-1]), out)


# a load step this much shorter than the longest one that still fails means the
# path is blocked (elements at the probe's edges about to invert); bisecting
# further only spends time (on the demo, 90 s down to 1e-3 before giving up)
MIN_STEP_FRACTION = 1.0 / 64


# a factorization (with its tangent) costs about as much as 25 iterations; a
# travel's factor that converged its equilibrium within this many iterations is
# kept for the next solve's warm start rather than refactorized there (on the
# demo this saved 3 of the cold walk's 14 factorizations, and 3 of the 4 a
# refresh inside a fit made when the moduli ratios had moved by more than 10%)
KEEP_ITERATIONS = 12
# factors sharing one analysis: the linear one, one per requested travel, the walk's and a spare
FACTOR_SLOTS = 16


def anderson_step(X: list[np.ndarray], G: list[np.ndarray]) -> np.ndarray:
    """The Anderson-mixed step from the iterates ``X`` and their fixed-point steps
    ``G`` (oldest first; the last step alone when there is one pair): the last
    step less the combination of the earlier differences that best cancels it."""
    g = G[-1]
    if len(G) < 2:
        return g
    dG = np.column_stack([G[j + 1] - G[j] for j in range(len(G) - 1)])
    dX = np.column_stack([X[j + 1] - X[j] for j in range(len(X) - 1)])
    gamma, *_ = np.linalg.lstsq(dG, g, rcond=None)
    return g - (dX + dG) @ gamma


class _StepFailed(Exception):
    """A load step did not converge (or its predictor inverted an element)."""


@dataclass
class _Preconditioner:
    factor: SymmetricFactor
    ratios: np.ndarray  # moduli ratios (to the first region) it was built for
    scale: float  # modulus of the first region it was built with
    at_equilibrium: bool = False  # the tangent of a converged state (not of an iterate)


def _near(ratios: np.ndarray, other: np.ndarray, factor: float = 1.5) -> bool:
    return bool(np.max(np.abs(np.log(ratios / other))) <= np.log(factor))


# a positive-weight rule of degree 3 (Stroud's conical product of 2-point
# Gauss-Jacobi rules): beside the probe's edges, where the deformation is
# largest, the linear model's 4-point rule let P2 elements deform in ways it does
# not see (on a fresh mesh of the demo the load path stopped at 13.9 of 14.8 mm,
# a corner element at det F = 0.25 in a nearly incompressible material); with
# these 8 points there the same mesh reached 14.8 mm. Both rules integrate the
# small-strain stiffness exactly, so the linear limit is unchanged.
def _conical_rule(n: int = 2) -> tuple[np.ndarray, np.ndarray]:
    from scipy.special import roots_jacobi

    def gauss_jacobi(a):  # on [0, 1] with the weight (1 - x)^a
        x, w = roots_jacobi(n, a, 0)
        return (x + 1) / 2, w / 2 ** (a + 1)

    (u, wu), (v, wv), (w, ww) = gauss_jacobi(2), gauss_jacobi(1), gauss_jacobi(0)
    U, V, W = (a.ravel() for a in np.meshgrid(u, v, w, indexing="ij"))
    weights = np.einsum("i,j,k->ijk", wu, wv, ww).ravel()
    x1, x2, x3 = U, V * (1 - U), W * (1 - U) * (1 - V)
    return np.column_stack([1 - x1 - x2 - x3, x1, x2, x3]), weights / weights.sum()


EDGE_BARY, EDGE_W = _conical_rule()


def edge_elements(mesh, rings: int = 1) -> np.ndarray:
    """Indices of the tets that touch the probe face's outline on the top face
    (vertices on its four sides), and ``rings`` more layers of their neighbours."""
    x0, x1, y0, y1 = mesh.probe_rect_mm
    P = mesh.points_mm
    top = mesh.top_nodes()
    scale = max(x1 - x0, y1 - y0)
    tol = 1e-6 * scale
    inside = (P[:, 0] > x0 - tol) & (P[:, 0] < x1 + tol) & (P[:, 1] > y0 - tol) & (P[:, 1] < y1 + tol)
    on_side = (np.minimum.reduce([np.abs(P[:, 0] - x0), np.abs(P[:, 0] - x1),
                                  np.abs(P[:, 1] - y0), np.abs(P[:, 1] - y1)]) < tol)
    mark = top & inside & on_side
    T = mesh.tets
    sel = mark[T].any(axis=1)
    for _ in range(rings):
        mark = np.zeros(len(P), bool)
        mark[T[sel].ravel()] = True
        sel = mark[T].any(axis=1)
    return np.flatnonzero(sel)


class _Group:
    """Elements that share a quadrature rule: their shape-function gradients in the
    reference configuration (m, q, 10, 3) and quadrature weights times volume (m, q)."""

    def __init__(self, idx, bary, weights, space, dofs):
        self.idx = np.asarray(idx, np.int64)
        self.dN = np.ascontiguousarray(shape_gradients(bary, space.grad_bary[self.idx], space.degree))
        self.wV = space.volumes_mm3[self.idx, None] * weights[None, :]
        self.dofs = dofs[self.idx]  # (m, 30)
        self.pos = None  # positions of its element entries in the tangent's upper triangle (set by the model)
        self.points = None  # its quadrature points' columns in the model's by-component arrays (set by the model)

    def gradient_entries(self, first_point: int, n_points: int):
        """COO entries (rows, columns, values) of this group's block of the gradient
        operator: row ``c * n_points + p`` is the displacement gradient's component
        c = 3 i + J at quadrature point p (this group's points numbered from
        ``first_point``, element-major)."""
        m, q = self.wV.shape
        point = first_point + np.arange(m * q).reshape(m, q, 1)
        rows, cols, vals = [], [], []
        for i in range(3):
            for J in range(3):
                rows.append(np.broadcast_to((3 * i + J) * n_points + point, (m, q, 10)).ravel())
                cols.append(np.broadcast_to(self.dofs[:, None, i::3], (m, q, 10)).ravel())
                vals.append(self.dN[..., J].ravel())
        return np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)

    def tangents(self, Fc, mu_e, lam_e) -> np.ndarray:
        """Element tangent stiffness (m, 10, 3, 10, 3) in mN/mm from this group's
        deformation gradients by component (9, m q; see :func:`_law`).

        With H = F^-T and h_a = H grad N_a:
        K[a i, b k] = int mu delta_ik grad N_a . grad N_b + (mu - lam ln J) h_ak h_bi + lam h_ai h_bk.
        """
        m, q = self.wV.shape
        J, cof = _cofactors(Fc)
        if not np.all(J > 0):
            raise ValueError("inverted element (det F <= 0)")
        H = (cof / J).T.reshape(m, q, 3, 3)
        J = J.reshape(m, q)
        h = np.einsum("mqIJ,mqaJ->mqaI", H, self.dN, optimize=True)
        w_mu = self.wV * mu_e[:, None]
        w2 = self.wV * (mu_e[:, None] - lam_e[:, None] * np.log(J))
        w3 = self.wV * lam_e[:, None]
        S = np.einsum("mq,mqaJ,mqbJ->mab", w_mu, self.dN, self.dN, optimize=True)
        X = h.reshape(m, q, 30)  # columns (a, k)
        XT = np.ascontiguousarray(X.transpose(0, 2, 1))
        K = (XT @ (w3[:, :, None] * X)).reshape(m, 10, 3, 10, 3)  # lam h_ai h_bk
        K2 = (XT @ (w2[:, :, None] * X)).reshape(m, 10, 3, 10, 3)  # [a, k, b, i]
        K += K2.transpose(0, 1, 4, 3, 2)
        for i in range(3):
            K[:, :, i, :, i] += S
        return K


class HyperelasticModel:
    """Neo-Hookean equilibria on an FE model's mesh, P2 space and boundary
    partition (the same as the linear model's).

    Each load step is solved by Anderson-accelerated modified Newton: the fixed
    matrix is a factorized tangent. A solve reuses the equilibria and tangents
    that earlier solves left at each requested travel (for moduli ratios within
    a factor 1.5), so in a fit only the first solve walks the load path and pays
    for factorizations; a step that converges slowly refactorizes at its current
    iterate (a Newton step). At every requested travel the tangent at the
    equilibrium is kept (refactorized when the ratios moved by more than 10% or
    the step needed more than 10 iterations).

    ``tol``: relative residual (free-dof internal force over the probe-dof
    internal force) at which a load step has converged. ``max_step_fraction``:
    the longest step of the load path walk, as a fraction of the specimen's
    height (shorter steps converge in fewer iterations; the tangent is
    refactorized only where a step is slow). ``reform_rate``: a step is slow
    when three iterations reduce the residual by less than this cubed.
    ``warm_starts``: keep the equilibrium and a factorized tangent at every
    requested travel (one factor each); off for a single solve (the simulator's
    truth), which then holds one working factor besides the linear one. A
    travel's own factor is kept only while the memory left can hold another
    (:func:`app.core.memory.can_hold`); otherwise the travel keeps its
    equilibrium alone, and a warm start from it iterates with the nearest kept
    factor (:attr:`n_lean` counts those travels). On the boxed phantom's finer
    mesh each factor holds about 0.5 GB, and the seven of a diagnosis' walk had
    taken it to 8.3 GB.
    """

    def __init__(self, fe: FEModel, tol: float = 1e-6, max_iterations: int = 60, anderson_depth: int = 5,
                 reform_rate: float = 0.85, single: bool = True, max_step_fraction: float = 0.02,
                 warm_starts: bool = True, edge_rule: bool = True):
        self.fe = fe
        self.warm_starts = warm_starts
        self._walk: tuple[float, _Preconditioner] | None = None  # the walk's working tangent (travel, factor)
        self._requested: set = set()
        self.max_step_fraction = max_step_fraction
        z = fe.space.points_mm[:, 2]
        self.height_mm = float(z.max() - z.min())
        self.tol, self.max_iterations, self.depth = tol, max_iterations, anderson_depth
        self._ordering = None  # the tangents' fill-reducing permutation, from the first factor
        self.reform_rate, self.single = reform_rate, single
        space = fe.space
        self.elems = space.elems
        self.n_dofs = space.n_dofs
        m = len(self.elems)
        self.dofs = (3 * self.elems[:, :, None] + np.arange(3)).reshape(m, -1)  # (m, 30)
        # quadrature: the linear model's four points, and eight beside the probe's outline
        # (see edge_elements); both rules are exact for the small-strain stiffness
        self.edge = edge_elements(fe.space.mesh) if edge_rule else np.zeros(0, np.int64)
        rest = np.setdiff1d(np.arange(m), self.edge)
        self._groups = [_Group(idx, bary, w, space, self.dofs) for idx, bary, w in
                        ((rest, QUAD_BARY, QUAD_W), (self.edge, EDGE_BARY, EDGE_W)) if len(idx)]
        self._setup_pattern()
        self._setup_gradient()
        self._cache: dict[float, _Preconditioner] = {}
        self._scratch: _Preconditioner | None = None  # a spare factor for trial tangents
        self._equilibria: dict[float, tuple[np.ndarray, np.ndarray]] = {}  # travel -> (ratios, u)
        self._lean: set = set()  # travels whose equilibrium is kept without a factor (memory short)
        self._lean_ever: set = set()  # travels that went without a factor of their own at some point
        self.n_factorizations = 0
        self.n_back_solves = 0
        self.n_residuals = 0
        self.trace: list = []

    # --- the residual: one sparse product each way -----------------------------
    def _setup_gradient(self):
        """The gradient operator G (9 n_points, n_dofs), u -> the displacement
        gradient at every quadrature point by component, and the points' weights
        and elements. The internal force is G^T (w P(I + G u)): two sparse products
        and the law on contiguous components, about twice as fast as the element
        by element einsums and scatter it replaced (54 -> 25 ms at paper size)."""
        sizes = [g.wV.size for g in self._groups]
        n_points, first = sum(sizes), np.cumsum([0] + sizes)
        for g, s in zip(self._groups, first):
            g.points = slice(int(s), int(s) + g.wV.size)  # its columns of the by-component arrays
        parts = [g.gradient_entries(g.points.start, n_points) for g in self._groups]
        rows, cols, vals = (np.concatenate(x) for x in zip(*parts))
        self._G = sp.csr_matrix((vals, (rows, cols)), shape=(9 * n_points, self.n_dofs))
        self._G.sort_indices()
        self._w = np.concatenate([g.wV.ravel() for g in self._groups])
        self._point_elem = np.concatenate([np.repeat(g.idx, g.wV.shape[1]) for g in self._groups])

    # --- sparsity: element entries -> upper triangle of the free-free block -----
    def _setup_pattern(self):
        fe, op = self.fe, self.fe.op
        # position of every CSR entry of the free-free block in the full pattern
        ff_rows = np.repeat(np.arange(len(fe.free)), np.diff(fe._ff_pattern[1]))
        ff_cols = fe._ff_pattern[0]
        upper = ff_cols >= ff_rows
        self._ffu_indptr = np.concatenate([[0], np.cumsum(np.bincount(ff_rows[upper], minlength=len(fe.free)))])
        self._ffu_indices = ff_cols[upper]
        n_ffu = int(upper.sum())
        full_to_ffu = np.full(len(op.indices), n_ffu, np.int64)  # n_ffu: not in the upper free-free block
        full_to_ffu[fe._pos_ff[upper]] = np.arange(n_ffu)
        pos = full_to_ffu[element_positions(op.indptr, op.indices, self.elems)].astype(np.int32)
        for g in self._groups:
            g.pos = pos[g.idx].ravel()
        self._n_ffu = n_ffu
        self._diag = self._ffu_indptr[:-1]  # each row's first upper entry is its diagonal
        assert np.array_equal(self._ffu_indices[self._diag], np.arange(len(fe.free)))

    # --- pieces ----------------------------------------------------------------
    def element_moduli(self, youngs_kPa, nu: float) -> tuple[np.ndarray, np.ndarray]:
        lab = self.fe.space.labels
        mus, lams = np.array([lame(float(E), nu) for E in youngs_kPa]).T
        return mus[lab], lams[lab]

    def deformation_gradients(self, u: np.ndarray) -> np.ndarray:
        """F at every quadrature point, by component (9, n_points; see :func:`_law`)."""
        Fc = (self._G @ u).reshape(9, -1)
        Fc[[0, 4, 8]] += 1.0
        return Fc

    def internal_force(self, u: np.ndarray, mu_e: np.ndarray, lam_e: np.ndarray, with_energy: bool = False):
        """f_int (n_dofs,) in mN: the derivative of the stored energy; with
        ``with_energy``, (f_int, stored energy) from one deformation gradient."""
        self.n_residuals += 1
        P, W = _law(self.deformation_gradients(u), mu_e[self._point_elem], lam_e[self._point_elem], self._w)
        f = self._G.T @ P.ravel()
        return (f, float(self._w @ W)) if with_energy else f

    def energy(self, u: np.ndarray, mu_e: np.ndarray, lam_e: np.ndarray) -> float:
        """Stored energy in kPa mm^3 (= uJ)."""
        _, W = _law(self.deformation_gradients(u), mu_e[self._point_elem], lam_e[self._point_elem])
        return float(self._w @ W)

    def tangent_upper(self, u, mu_e, lam_e) -> np.ndarray:
        """Values of the upper triangle of the free-free tangent (CSR order)."""
        out = np.zeros(self._n_ffu + 1)
        Fc = self.deformation_gradients(u)
        for g in self._groups:  # each group's element matrices straight into the sum
            K = g.tangents(Fc[:, g.points], mu_e[g.idx], lam_e[g.idx])
            out += np.bincount(g.pos, weights=K.ravel(), minlength=self._n_ffu + 1)
        return out[: self._n_ffu]

    def _upper_matrix(self, data) -> sp.csr_matrix:
        n = len(self.fe.free)
        return sp.csr_matrix((data, self._ffu_indices, self._ffu_indptr), shape=(n, n))

    def _factor(self, data) -> SymmetricFactor:
        """A new factor; every tangent has the same pattern, so it shares a live
        factor's analysis (else reuses its ordering: METIS once)."""
        self.n_factorizations += 1
        live = next(iter(self._held()), None)
        f = SymmetricFactor(self._upper_matrix(data), single=self.single, definite=True, ordering=self._ordering,
                            share=live and live.factor, slots=FACTOR_SLOTS)
        self._ordering = f.ordering
        return f

    def _held(self) -> list[_Preconditioner]:
        """The preconditioners this model holds: the travels' (the linear one's
        included), the walk's and the spare."""
        return [p for p in (*self._cache.values(), self._walk and self._walk[1], self._scratch) if p]

    @property
    def n_lean(self) -> int:
        """How many requested travels went without a factor of their own (memory short)."""
        return len(self._lean_ever)

    def _may_keep_factor(self, d: float) -> bool:
        """Whether travel ``d`` may keep a factor of its own: the memory left can
        hold one more (the size of a live one), else it is noted (:attr:`n_lean`)."""
        live = next(iter(self._held()), None)
        if live is None or memory.can_hold(live.factor.memory_bytes):
            return True
        self._lean_ever.add(d)
        self.trace.append((d, "memory short: no factor of its own kept"))
        return False

    def free(self) -> None:
        for p in self._cache.values():
            p.factor.free()
        self._cache.clear()
        self._equilibria.clear()
        self._lean.clear()
        if self._walk is not None:
            self._walk[1].factor.free()
            self._walk = None
        if self._scratch is not None:
            self._scratch.factor.free()
            self._scratch = None

    # --- solve -----------------------------------------------------------------
    def solve(self, youngs_kPa, nu: float, depths_mm, *, progress: Callable[[int, int], None] | None = None,
              cancel: threading.Event | None = None) -> HyperelasticSolution:
        """Equilibria at increasing probe travels ``depths_mm`` (the load steps).

        ``progress(step, n_steps)`` after each step; ``cancel`` stops between iterations.
        """
        with single_threaded_blas():  # numpy's spinning BLAS threads slowed PARDISO's back-substitutions
            return self._solve(youngs_kPa, nu, depths_mm, progress, cancel)

    def _solve(self, youngs_kPa, nu, depths_mm, progress, cancel) -> HyperelasticSolution:
        fe = self.fe
        theta = np.asarray(youngs_kPa, float)
        depths = np.asarray(depths_mm, float)
        if np.any(np.diff(depths) <= 0) or depths[0] <= 0:
            raise ElastoidError("load steps must be increasing positive probe travels")
        mu_e, lam_e = self.element_moduli(theta, nu)
        ratios = theta / theta[0]
        free, fixed = fe.free, fe.fixed
        prev: list[np.ndarray] = []
        forces, fields, iters = [], [], []
        done_d: list[float] = []
        todo: list[float] = []
        self._requested = {float(x) for x in depths} if self.warm_starts else set()
        max_step = self.max_step_fraction * self.height_mm
        i, n_sub = 0, 0
        while todo or i < len(depths):
            if not todo:  # the next requested travel: directly from a kept equilibrium, else in substeps
                d_req = float(depths[i])
                i += 1
                d_prev = done_d[-1] if done_d else 0.0
                n = 1 if self._warm_start(d_req, ratios) else max(1, math.ceil((d_req - d_prev) / max_step - 1e-9))
                todo = list(d_prev + (d_req - d_prev) * np.arange(1, n + 1) / n)
                todo[-1] = d_req
            d = todo[0]
            try:
                u, n_it, n_kept = self._step(d, done_d, prev, theta, ratios, nu, mu_e, lam_e, cancel)
            except _StepFailed:
                # bisect: an intermediate load step first (kept out of the result)
                d_prev = done_d[-1] if done_d else 0.0
                n_sub += 1
                if n_sub > 8 * len(depths) or d - d_prev < MIN_STEP_FRACTION * min(max_step, d_req):
                    raise ElastoidError(
                        f"the hyperelastic solve cannot follow the load path beyond {d_prev:.3g} mm of probe travel "
                        f"(steps of {d - d_prev:.2g} mm fail: elements beside the probe's edges are close to "
                        "inverting)") from None
                todo.insert(0, 0.5 * (d_prev + d))
                continue
            todo.pop(0)
            done_d.append(d)
            prev.append(u.copy())
            if d == d_req:
                if self.warm_starts:
                    self._remember(d, u, ratios, mu_e, lam_e, theta, n_kept)
                f = self.internal_force(u, mu_e, lam_e)
                forces.append(-float(fe.probe_z @ f[fixed]) * MN_TO_N)
                fields.append(u.copy())
                iters.append(n_it)
                if progress:
                    progress(len(forces), len(depths))
        return HyperelasticSolution(depths, np.array(forces), np.array(fields), tuple(iters))

    def _remember(self, d, u, ratios, mu_e, lam_e, theta, n_kept) -> None:
        """Keep the equilibrium at travel ``d``, and a factorized tangent for it:
        the one this travel's iteration ended with when it converged within
        KEEP_ITERATIONS with it (evidently good enough here), else the tangent
        factorized at the equilibrium. ``n_kept``: iterations done with the
        travel's last factor."""
        self._equilibria[d] = (ratios.copy(), u.copy())
        self._lean.discard(d)
        own = self._cache.get(d)
        if own is not None and n_kept <= KEEP_ITERATIONS:
            own.at_equilibrium = True
            return
        if own is None:
            if not self._may_keep_factor(d):  # the equilibrium alone: a warm start uses a neighbour's factor
                self._lean.add(d)
                return
            own, self._scratch = self._scratch, None
        own = self._definite_into(own, self.tangent_upper(u, mu_e, lam_e) / theta[0], ratios, True)
        if own.factor.positive_definite is False:  # not a stable equilibrium: no warm start from it
            self._cache.pop(d, None)
            self._recycle(own)
        else:
            self._cache[d] = own

    def _recycle(self, p: _Preconditioner) -> None:
        """Keep a factor no longer needed as the spare (refactorizing it later skips
        the analysis a new one needs), or free it when there is a spare already."""
        if self._scratch is None:
            self._scratch = p
        elif p is not self._scratch:
            p.factor.free()

    def _factor_into(self, p: _Preconditioner | None, data, ratios, at_equilibrium: bool) -> _Preconditioner:
        """``p`` refactorized with the tangent values ``data`` (a new factor if None)."""
        if p is None:
            return _Preconditioner(self._factor(data), ratios, 1.0, at_equilibrium)
        p.factor.refactor(data)
        self.n_factorizations += 1
        p.ratios, p.scale, p.at_equilibrium = ratios, 1.0, at_equilibrium
        return p

    def _warm_start(self, d: float, ratios: np.ndarray) -> tuple[np.ndarray, _Preconditioner | None] | None:
        """The equilibrium and tangent kept at travel ``d`` for nearby ratios, if any
        (the tangent None when memory was short and the equilibrium was kept alone)."""
        kept, pre = self._equilibria.get(d), self._cache.get(d)
        if kept is None or not _near(ratios, kept[0]):
            return None
        if pre is not None and pre.at_equilibrium:
            return kept[1], pre
        if pre is None and d in self._lean:
            return kept[1], None
        return None

    def _step(self, d, done_d, prev, theta, ratios, nu, mu_e, lam_e, cancel):
        """One load step: from the equilibrium an earlier solve left at this travel
        (nearby ratios), else from the last converged steps (extrapolated predictor)."""
        fe = self.fe
        free, fixed = fe.free, fe.fixed
        warm = self._warm_start(d, ratios)
        if warm is not None:
            u, pre = warm[0].copy(), warm[1]
            if pre is None:  # kept without its own factor: the nearest one, else the linear stiffness
                pre = self._nearest(d, ratios) or self._linear_preconditioner(theta, nu)
            u[fixed] = d * fe.lift
            try:
                return self._equilibrate(u, d, theta, ratios, mu_e, lam_e, pre, cancel, nu)
            except _StepFailed:
                self.trace.append((d, "warm start failed"))
        if len(prev) >= 2:  # quadratic extrapolation through 0 and the last two steps
            d0, d1 = done_d[-2], done_d[-1]
            a1 = (prev[-1] / d1 - prev[-2] / d0) / (d1 - d0)
            u = (a1 * d + (prev[-1] / d1 - a1 * d1)) * d
        elif prev:
            u = prev[-1] * (d / done_d[-1])
        else:
            u = np.zeros(self.n_dofs)
        u[fixed] = d * fe.lift
        pre = self._nearest(d, ratios)
        if pre is None:  # no tangent near this step yet: the linear stiffness
            pre = self._linear_preconditioner(theta, nu)
        if not prev:  # the linear solution
            _, b, _, _ = fe.term_blocks(coefficients(ratios, nu))
            u[free] = d * self._linear_preconditioner(theta, nu).factor.solve(b)
        return self._equilibrate(u, d, theta, ratios, mu_e, lam_e, pre, cancel, nu)

    def _nearest(self, d: float, ratios: np.ndarray) -> _Preconditioner | None:
        best, dist = None, np.inf
        if self._walk is not None and _near(ratios, self._walk[1].ratios):
            best, dist = self._walk[1], abs(self._walk[0] - d)
        for dk, p in self._cache.items():
            if dk <= 0 or not _near(ratios, p.ratios):
                continue
            if abs(dk - d) < dist:
                best, dist = p, abs(dk - d)
        return best

    def _linear_preconditioner(self, theta, nu) -> _Preconditioner:
        ratios = theta / theta[0]
        p = self._cache.get(0.0)
        if p is None or not _near(ratios, p.ratios):
            mu_e, lam_e = self.element_moduli(ratios, nu)
            p = self._factor_into(p, self.tangent_upper(np.zeros(self.n_dofs), mu_e, lam_e), ratios, False)
            if p.factor.positive_definite is False:  # not kept: its ratios would pass for a valid factor's
                self._cache.pop(0.0, None)
                p.factor.free()
                raise ElastoidError("the linear stiffness is not positive definite: the specimen is not held "
                                    "(check the boundary conditions) or a region's modulus is not positive")
            self._cache[0.0] = p
        return p

    def _equilibrate(self, u, d, theta, ratios, mu_e, lam_e, pre: _Preconditioner, cancel, nu: float):
        """Anderson-accelerated modified Newton on the free dofs. When the
        iteration is slow, the tangent at the current iterate is factorized (a
        Newton step) and kept for this load step. Returns the equilibrium, the
        iterations, and how many of them used the travel's own kept factor
        (inf when another one served)."""
        free, fixed = self.fe.free, self.fe.fixed
        x = u[free].copy()
        X, G, hist = [], [], []
        ref, last_good, e_good, n_cut = None, None, None, 0
        since = 0  # the iteration at which ``pre`` was last factorized here
        for it in range(1, self.max_iterations + 1):
            if cancel is not None and cancel.is_set():
                raise Cancelled("hyperelastic solve cancelled")
            u[free] = x
            try:
                f, e = self.internal_force(u, mu_e, lam_e, with_energy=True)
            except ValueError:  # an inverted element: back towards the last good iterate
                if last_good is None:
                    raise _StepFailed(d) from None
                x = 0.5 * (x + last_good)
                X, G = [], []
                continue
            # equilibrium minimizes the stored energy over the free dofs: a step that
            # raises it overshot (far from the solution the tangent's step can), so it
            # is cut back towards the last iterate (a backtracking line search)
            if e_good is not None and e > e_good + 1e-10 * abs(e_good) and n_cut < 6:
                n_cut += 1
                x = last_good + 0.5 * (x - last_good)
                X, G = [], []
                continue
            n_cut = 0
            e_good = e
            r = f[free]
            if ref is None:
                ref = max(np.linalg.norm(f[fixed]), 1e-300)
            hist.append(np.linalg.norm(r) / ref)
            self.trace.append((d, hist[-1]))
            if hist[-1] <= self.tol:
                # iterations done with the travel's own factor (for _remember)
                return u, it, (it - since if pre is self._cache.get(d) else math.inf)
            last_good = x.copy()
            slow = (len(hist) > 3 and hist[-1] > self.reform_rate ** 3 * hist[-4]) or hist[-1] > 2 * min(hist)
            if slow:
                new = self._try_factor(self.tangent_upper(u, mu_e, lam_e) / theta[0], ratios)
                if new is None:
                    # the tangent at this iterate is indefinite (off the stable path, e.g.
                    # at a predictor beside the probe's edges): its Newton step need not
                    # lower the energy, and iterating with it stalls; keep the factor in use
                    self.trace.append((d, "indefinite tangent kept out"))
                else:
                    # a requested travel keeps its own factor (for later warm starts); the
                    # walk's intermediate steps share one
                    if d in self._requested and (d in self._cache or self._may_keep_factor(d)):
                        old, self._cache[d] = self._cache.get(d), new
                    else:
                        old, self._walk = (self._walk[1] if self._walk else None), (d, new)
                    if old is not None:  # recycled as the next trial factor (a refactorization
                        self._recycle(old)  # skips the symbolic analysis a new factor needs)
                    pre, since = new, it
                    self.trace.append((d, "reform"))
                X, G, hist = [], [], [hist[-1]]
            self.n_back_solves += 1
            g = -pre.factor.solve(r) / (theta[0] * pre.scale)
            if r @ g >= 0:  # not a descent direction (cannot happen with a positive definite factor)
                lin = self._linear_preconditioner(theta, nu)
                self.trace.append((d, "ascent; linear stiffness used"))
                g = -lin.factor.solve(r) / theta[0]
                X, G = [], []
            X.append(x.copy())
            G.append(g)
            if len(X) > self.depth + 1:
                X.pop(0)
                G.pop(0)
            step = anderson_step(X, G)
            if len(G) >= 2 and r @ step >= 0:  # the mixed step would raise the energy: the plain one
                step = g
                X, G = [x.copy()], [g]
            x = x + step
        raise _StepFailed(d)

    def _try_factor(self, data, ratios) -> _Preconditioner | None:
        """A factor of the tangent values ``data`` (into the spare factor), or None
        when the matrix is not positive definite (its Cholesky factorization fails)."""
        p = self._definite_into(self._scratch, data, ratios, False)
        if p.factor.positive_definite is False:
            self._scratch = p
            return None
        self._scratch = None
        return p

    def _definite_into(self, p: _Preconditioner | None, data, ratios, at_equilibrium: bool) -> _Preconditioner:
        """``p`` (a new factor if None) refactorized with the tangent values ``data``,
        shifted towards their diagonal (a Levenberg-Marquardt step, between Newton's
        and steepest descent's) until positive definite, by up to 100%; check
        ``p.factor.positive_definite``."""
        p = self._factor_into(p, data, ratios, at_equilibrium)
        shift = 1e-3
        while p.factor.positive_definite is False and shift <= 1.0:
            shifted = data.copy()
            shifted[self._diag] *= 1.0 + shift
            p.factor.refactor(shifted)
            self.n_factorizations += 1
            shift *= 10.0
        return p
