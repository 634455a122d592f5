"""The forward model: displacement field and probe force for given moduli.

Boundary conditions (the paper's): bottom face bonded to the table, probe face
bonded and pushed down by the probe travel d. Linear elasticity makes the
solution proportional to d, so everything is computed for d = 1 mm and scaled.

Online evaluations go through a reduced basis (:class:`ReducedModel`): one
factorization at a reference point, then back-substitutions on preconditioned
residuals enrich the basis until the Galerkin residual is below tolerance over
the whole parameter range. The residual is evaluated exactly (through a small
QR factor), so an evaluation outside the trained range enriches itself.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from app.core.fem import AffineOperator, P2Space, assemble, coefficients, interpolation_matrix, p2_space
from app.core.mesh import TetMesh
from app.core.solver import Factorized, preconditioner

MN_TO_N = 1e-3  # K u is in mN with kPa and mm


@dataclass(frozen=True)
class Boundary:
    bottom: str = "bonded"  # "bonded" | "sliding"
    probe: str = "bonded"  # "bonded" | "slip"


@dataclass
class FEModel:
    """Mesh + P2 space + assembled operator + boundary partition."""

    space: P2Space
    op: AffineOperator
    boundary: Boundary
    free: np.ndarray  # indices of free dofs
    fixed: np.ndarray  # indices of constrained dofs
    lift: np.ndarray  # (n_fixed,) prescribed value per mm of probe travel
    probe_z: np.ndarray  # (n_fixed,) 1 on the probe's z dofs
    _pos_ff: np.ndarray = field(repr=False, default=None)
    _ff_pattern: tuple = field(repr=False, default=None)

    @property
    def n_regions(self) -> int:
        return len(self.space.mesh.region_names)

    def term_blocks(self, coeffs: dict):
        """(A_ff, b_f, h, c) for K = sum coeffs K_key: A_ff u_f = b_f with u_c = lift,
        force in mN per mm = -(h . u_f + c)."""
        vals = self.op.values(coeffs)
        K = sp.csr_matrix((vals, self.op.indices, self.op.indptr), shape=self.op.shape)
        A = self._free_block(vals)
        # products with vectors that vanish on the free dofs, rather than K's
        # fixed blocks sliced out (two row slices of the whole K were 0.1 s a
        # term at paper size); K is symmetric, so K[fixed, free]^T z = (K z)[free]
        lift, probe = np.zeros(K.shape[0]), np.zeros(K.shape[0])
        lift[self.fixed], probe[self.fixed] = self.lift, self.probe_z
        K_lift = K @ lift
        b = -K_lift[self.free]
        Kcf_s = (K @ probe)[self.free]
        c = float(probe @ K_lift)
        return A, b, Kcf_s, c

    def term_matrix(self, coeffs: dict) -> sp.csr_matrix:
        """A_ff of :meth:`term_blocks` alone (the same values, without the whole K)."""
        return self._free_block(self.op.values(coeffs))

    def _free_block(self, vals: np.ndarray) -> sp.csr_matrix:
        return sp.csr_matrix((vals[self._pos_ff], *self._ff_pattern), shape=(len(self.free), len(self.free)))

    def solve(self, youngs_kPa, nu: float = 0.49):
        """Full-order solve for d = 1 mm: (u (n_dofs,), force N per mm)."""
        A, b, h, c = self.term_blocks(coefficients(youngs_kPa, nu))
        f = Factorized(A)
        try:
            uf = f.solve(b)
        finally:
            f.free()
        u = np.zeros(self.space.n_dofs)
        u[self.free] = uf
        u[self.fixed] = self.lift
        return u, -(h @ uf + c) * MN_TO_N


def build_model(mesh: TetMesh, boundary: Boundary = Boundary(), op: AffineOperator | None = None) -> FEModel:
    """Assemble (unless ``op`` is given) and partition the dofs for ``boundary``."""
    space = op.space if op is not None else p2_space(mesh)
    op = op if op is not None else assemble(space)
    pts = space.points_mm
    n = space.n_nodes
    fixed = np.zeros((n, 3), bool)
    lift = np.zeros((n, 3))
    bottom = pts[:, 2] < 1e-6
    probe = mesh.probe_nodes(pts)
    if boundary.bottom == "bonded":
        fixed[bottom] = True
    else:
        fixed[bottom, 2] = True
    if boundary.probe == "bonded":
        fixed[probe] = True
    else:
        fixed[probe, 2] = True
    lift[probe, 2] = -1.0
    if boundary.bottom != "bonded" and boundary.probe != "bonded":
        # remove rigid in-plane motions: pin x, y of the bottom node nearest the
        # centre and y of the bottom node nearest the middle of the x = sx edge
        sx, sy, _ = mesh.size_mm
        ib = np.flatnonzero(bottom)
        c0 = ib[np.argmin(np.linalg.norm(pts[ib, :2] - [sx / 2, sy / 2], axis=1))]
        c1 = ib[np.argmin(np.linalg.norm(pts[ib, :2] - [sx, sy / 2], axis=1))]
        fixed[c0, :2] = True
        fixed[c1, 1] = True
    fixed_f = fixed.ravel()
    free_idx = np.flatnonzero(~fixed_f)
    fixed_idx = np.flatnonzero(fixed_f)
    probe_z = np.zeros((n, 3))
    probe_z[probe, 2] = 1.0
    # positions of the free-free block inside the shared CSR pattern
    pattern = sp.csr_matrix((np.arange(1, len(op.indices) + 1, dtype=float), op.indices, op.indptr), shape=op.shape)
    sub = pattern[free_idx][:, free_idx].tocsr()
    sub.sort_indices()
    pos = sub.data.astype(np.int64) - 1
    model = FEModel(space, op, boundary, free_idx, fixed_idx, lift.ravel()[fixed_idx], probe_z.ravel()[fixed_idx])
    model._pos_ff = pos
    model._ff_pattern = (sub.indices.copy(), sub.indptr.copy())
    return model


# ---------------------------------------------------------------------------
# reduced basis
# ---------------------------------------------------------------------------


def _own_entries(A: sp.csr_matrix) -> sp.csr_matrix:
    """``A`` without the zeros it holds in the shared pattern of every term: a
    region's term is zero outside the region's elements. Its products are then
    the same to the bit (only added zeros are dropped) over fewer entries: on the
    demo's mesh the tumour's term keeps 387,513 of 4,163,949, and each basis vector
    of a diagnosis' model costs one product per term."""
    A = sp.csr_matrix((A.data, A.indices.copy(), A.indptr.copy()), shape=A.shape)  # the pattern is shared
    A.eliminate_zeros()
    return A


class ReducedModel:
    """Galerkin reduced model over affine terms K_q (one per region, or per region
    and Lame kind when Poisson's ratio is free).

    ``terms`` lists coefficient dicts of the operator; the parameters are the
    term weights theta_q (e.g. Young's moduli in kPa). The residual of the full
    system, r = sum_q theta_q (b_q - A_q V a), is kept as an orthonormal basis of
    its possible directions with a small triangular factor, so its norm costs
    microseconds and stays accurate.
    """

    def __init__(self, model: FEModel, terms: list[dict], tol: float = 1e-7, max_basis: int = 80):
        self.model = model
        self.terms = terms
        self.tol = tol
        self.max_basis = max_basis
        blocks = [model.term_blocks(t) for t in terms]
        self._A = [_own_entries(b[0]) for b in blocks]
        self.b = np.array([b[1] for b in blocks])  # (Q, n): one right-hand side per term
        self.h = np.array([b[2] for b in blocks])
        self.c = np.array([b[3] for b in blocks])
        n, Q = len(model.free), len(terms)
        # vectors are stored as rows (contiguous), so the projections are fast BLAS calls
        self._Vt = np.zeros((max_basis, n))
        self._Qwt = np.zeros((Q * (max_basis + 1), n))
        self._Rw = np.zeros((Q * (max_basis + 1), Q * (max_basis + 1)))
        self._nw = 0
        self.k = 0
        # the reduced operator, grown by a row and a column per basis vector
        self._Ar = np.zeros((Q, max_basis, max_basis))
        self._br = np.zeros((Q, max_basis))
        self._hr = np.zeros((Q, max_basis))
        self._push_residual_columns(self.b)
        self._prec = None
        self._borrowed = False  # _prec is another reduced model's (see borrow_preconditioner)
        self.n_full_solves = 0
        self.n_back_solves = 0
        self._update_reduced()

    @property
    def V(self) -> np.ndarray:
        return self._Vt[: self.k].T

    @property
    def A(self) -> list:
        """The terms' free-free matrices A_q, which only an enrichment needs: freed by
        :meth:`release` and rebuilt (identically) from the FE model when asked for.
        Each holds only its own entries (see _own_entries)."""
        if self._A is None:
            self._A = [_own_entries(self.model.term_matrix(t)) for t in self.terms]
        return self._A

    # --- offline ------------------------------------------------------------
    def _push_residual_columns(self, W: np.ndarray) -> None:
        """Append the columns (rows of ``W``) to the orthonormal residual basis and its
        triangular factor by block classical Gram-Schmidt with reorthogonalization
        (BCGS2: each pass projects the whole block against the basis in one sweep over
        it, then orthonormalizes inside the block by a QR)."""
        j, m = self._nw, len(W)
        Qwt = self._Qwt[:j]
        W = np.asarray(W, float)
        S1 = Qwt @ W.T
        Q1, T1 = np.linalg.qr((W - S1.T @ Qwt).T)
        S2 = Qwt @ Q1
        Q2, T2 = np.linalg.qr((Q1.T - S2.T @ Qwt).T)
        self._Rw[:j, j : j + m] = S1 + S2 @ T1
        self._Rw[j : j + m, j : j + m] = T2 @ T1
        self._Qwt[j : j + m] = Q2.T
        self._nw += m

    def _matrix(self, theta):
        A = self.A[0] * theta[0]
        for q in range(1, len(theta)):
            A = A + self.A[q] * theta[q]
        return A

    def _rhs(self, theta):
        return sum(t * b for t, b in zip(theta, self.b))

    def _ensure_prec(self, theta):
        if self._borrowed and not self._prec.alive:  # its owner freed it: factorize one's own
            self._prec, self._borrowed = None, False
        if self._prec is None:
            self._prec = preconditioner(self._matrix(theta))
            self.n_full_solves += 1

    def factorize(self, theta) -> bool:
        """Make sure a factorization (its own, or a live borrowed one) is held, one of
        the stiffness at ``theta`` when one has to be made; other models may then
        borrow it. Returns whether it had to be made (its holder may want to
        :meth:`release` it after)."""
        had = self._prec is not None and self._prec.alive
        self._ensure_prec(np.asarray(theta, float))
        return not had

    def borrow_preconditioner(self, other: "ReducedModel") -> bool:
        """Enrich with ``other``'s factorized stiffness (a model on the same free
        dofs) instead of factorizing one's own, until :meth:`release`, which drops
        it without freeing it (``other`` owns it). Any fixed matrix close to the
        stiffness serves; the basis takes more vectors the further it is. On the
        demo's mesh, a model trained near 18 and 63 kPa
        with the factor of a homogeneous stiffness took 17 vectors instead of 9,
        to the same residual tolerance, and 1.5-2.5 s instead of 7.8-9.2 s (its own
        factorization). Should the owner free it first, the next enrichment
        factorizes this model's own. Returns whether it was borrowed."""
        if other._prec is None or not other._prec.alive or self._prec is not None or \
                not np.array_equal(self.model.free, other.model.free):
            return False
        self._prec, self._borrowed = other._prec, True
        return True

    def release(self) -> None:
        """Free the preconditioner's factorization (on the demo's 52,173 free dofs
        about 0.3 GB, double precision) and the terms' matrices (50 MB each there);
        an enrichment rebuilds both (the matrices in about 0.05 s each, beside the
        factorization's 0.5 s). A borrowed factorization is only dropped."""
        if self._prec is not None:
            if not self._borrowed:
                self._prec.free()
            self._prec, self._borrowed = None, False
        self._A = None

    def _add(self, v) -> bool:
        Vt = self._Vt[: self.k]
        for _ in range(2):  # twice is enough (Kahan)
            v = v - (Vt @ v) @ Vt
        nv = np.linalg.norm(v)
        if nv == 0 or self.k >= self.max_basis:
            return False
        v = v / nv
        k = self.k
        self._Vt[k] = v
        Av = np.array([A @ v for A in self.A])  # (Q, n), not kept: the residual basis holds what is needed
        self._push_residual_columns(Av)
        # the new column of each reduced matrix, O(n k), and its row by symmetry
        self._Ar[:, : k + 1, k] = Av @ self._Vt[: k + 1].T
        self._Ar[:, k, :k] = self._Ar[:, :k, k]
        self._br[:, k] = self.b @ v
        self._hr[:, k] = self.h @ v
        self.k += 1
        self._update_reduced()
        return True

    def _update_reduced(self):
        k = self.k
        self.Ar = self._Ar[:, :k, :k]
        self.br = self._br[:, :k]
        self.hr = self._hr[:, :k]
        self._R = self._Rw[: self._nw, : self._nw]

    def train(self, thetas: np.ndarray, progress=None):
        """Greedy enrichment until the relative residual is below ``tol`` at every
        training parameter (rows of ``thetas``)."""
        thetas = np.atleast_2d(np.asarray(thetas, float))
        self._ensure_prec(np.exp(np.log(thetas).mean(axis=0)))
        if self.k == 0:
            self._add(self._prec.solve(self._rhs(np.exp(np.log(thetas).mean(axis=0)))))
            self.n_back_solves += 1
        while self.k < self.max_basis:
            res = np.array([self.residual(t)[1] for t in thetas])
            worst = int(np.argmax(res))
            if progress:
                progress(self.k, float(res[worst]))
            if res[worst] < self.tol:
                break
            if not self._enrich(thetas[worst]):
                break

    def _enrich(self, theta) -> bool:
        """Add the preconditioned residual at ``theta`` to the basis. The residual
        is read from its orthonormal basis (one dense product) rather than
        recomputed from the terms' sparse matrices (one product each)."""
        theta = np.asarray(theta, float)
        r = self._residual_coefficients(theta, self.coords(theta, check=False)) @ self._Qwt[: self._nw]
        self.n_back_solves += 1
        return self._add(self._prec.solve(r))

    # --- online -------------------------------------------------------------
    def _solve_reduced(self, theta):
        return np.linalg.solve(np.tensordot(theta, self.Ar, axes=1), theta @ self.br)

    def coords(self, theta, check: bool = True) -> np.ndarray:
        """Reduced coordinates a with u_f = V a (per mm of probe travel)."""
        theta = np.asarray(theta, float)
        a = self._solve_reduced(theta)
        if check:
            while self.residual(theta, a)[1] >= self.tol and self.k < self.max_basis:
                self._ensure_prec(theta)
                if not self._enrich(theta):
                    break
                a = self._solve_reduced(theta)
        return a

    def residual(self, theta, a=None):
        """(absolute, relative) Euclidean residual of the full system at theta."""
        theta = np.asarray(theta, float)
        if a is None:
            a = self._solve_reduced(theta)
        Q = len(theta)
        r = np.linalg.norm(self._residual_coefficients(theta, a))
        bn = np.linalg.norm(self._R[:Q, :Q] @ theta)
        return r, r / max(bn, 1e-300)

    def _residual_coefficients(self, theta, a) -> np.ndarray:
        """The full system's residual at ``theta`` for reduced coordinates ``a``, as
        coefficients on the orthonormal residual basis (rows of ``_Qwt``)."""
        # column order: b_1..b_Q, then A_1 v_1..A_Q v_1, A_1 v_2, ...
        return self._R @ np.concatenate([theta, -np.outer(a, theta).ravel()])

    def force_N_per_mm(self, theta, a=None) -> float:
        theta = np.asarray(theta, float)
        if a is None:
            a = self.coords(theta)
        return float(-(theta @ (self.hr @ a) + theta @ self.c) * MN_TO_N)

    def full_field(self, a) -> np.ndarray:
        """Full displacement vector (n_dofs,) per mm for reduced coordinates a."""
        m = self.model
        u = np.zeros(m.space.n_dofs)
        u[m.free] = self.V @ a
        u[m.fixed] = m.lift
        return u

    def point_operator(self, points_mm: np.ndarray):
        """Displacements at fixed points, kept in step with the basis."""
        P = interpolation_matrix(self.model.space, points_mm)
        return _PointOperator(self, P[:, self.model.free], P[:, self.model.fixed] @ self.model.lift)


class _PointOperator:
    def __init__(self, rm: ReducedModel, Pf, lift_part):
        self.rm, self.Pf, self.lift_part = rm, Pf, lift_part
        self._n = -1
        self.B = None

    def values(self, a: np.ndarray) -> np.ndarray:
        """Displacement (n, 3) mm per mm of probe travel."""
        if self._n != self.rm.k:
            self.B = self.Pf @ self.rm.V
            self._n = self.rm.k
        return (self.B @ a + self.lift_part).reshape(-1, 3)


def region_terms(n_regions: int, nu: float) -> list[dict]:
    """One affine term per region with Poisson's ratio fixed: theta_r = E_r (kPa)."""
    out = []
    for r in range(n_regions):
        c = coefficients([1.0], nu)
        out.append({(r, "mu"): c[(0, "mu")], (r, "lam"): c[(0, "lam")]})
    return out


def local_training_set(moduli_kPa, factor: float = 3.0, n: int | None = None, seed: int = 0) -> np.ndarray:
    """Moduli (kPa) whose ratios to the first region lie within ``factor`` of those
    of ``moduli_kPa``: the training set of a refit that starts at a known optimum
    (a diagnosis candidate). Evaluations beyond it still enrich the basis (the
    residual is checked at every one), so this only saves training time.

    ``n``: points on the line of two regions' ratio (12 unless given), or random
    points in the box of more (96 unless given, beside the box's corners). A box
    needs them: the basis grows where the residual is worst among the points, and
    between too few of them it stays above the tolerance, so that a fit there
    enriches the basis again, with a factorization if the model's was released.
    On the demo's model with a located sphere (three regions, 72,288 free dofs),
    12 random points gave 45 basis vectors, and 42% of 300 other random points in
    the box had a residual above the tolerance (at most 2.5 times it); 96 gave 45
    vectors too, and none (training 9.5 s against 7.8 s, the factorization
    included)."""
    E = np.asarray(moduli_kPa, float)
    if n is None:
        n = 12 if len(E) <= 2 else 96
    return training_set(len(E), (1.0 / factor, factor), n, seed) * np.concatenate([[1.0], E[1:] / E[0]])


def line_training_set(moduli_kPa, index: int, factor: float = 3.0, n: int = 12) -> np.ndarray:
    """Moduli (kPa) with region ``index``'s alone varied within ``factor`` of
    ``moduli_kPa``'s, the others at theirs: the training set of a fit of that one
    modulus (the inclusion's at each trial sphere of its placement). A box of every
    ratio trains directions such a fit never uses: on a paper-size phantom with a
    located sphere, 17 basis vectors instead of 27, and 3.6 s a trial instead of
    6.2 s with the fit (docs/model-check.md, "The placement's cost"). The fit still
    enriches the basis wherever it goes."""
    E = np.asarray(moduli_kPa, float)
    out = np.tile(E / E[0], (n, 1))
    out[:, index] *= np.exp(np.linspace(-np.log(factor), np.log(factor), n))
    return out


def training_set(n_regions: int, ratio_range=(1 / 30, 30), n: int = 24, seed: int = 0) -> np.ndarray:
    """Moduli (kPa) covering the ratio range; the first region is the unit (scale is free)."""
    if n_regions == 1:
        return np.ones((1, 1))
    rng = np.random.default_rng(seed)
    lo, hi = np.log(ratio_range)
    if n_regions == 2:
        r = np.exp(np.linspace(lo, hi, n))
        return np.column_stack([np.ones(n), r])
    logs = rng.uniform(lo, hi, size=(n, n_regions - 1))
    corners = np.array(np.meshgrid(*[[lo, 0.0, hi]] * (n_regions - 1))).reshape(n_regions - 1, -1).T
    logs = np.vstack([corners, logs])
    return np.column_stack([np.ones(len(logs)), np.exp(logs)])
