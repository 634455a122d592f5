"""Small-strain linear elasticity on quadratic (10-node) tetrahedra.

The stiffness is affine in the material coefficients:

    K = sum over regions r of  mu_r * Kmu_r + lam_r * Klam_r

so the per-region matrices are assembled once and any set of moduli is a
linear combination of their value arrays over one shared sparsity pattern.
Quadratic elements keep nearly incompressible tissue (nu = 0.49) from locking.

Units: lengths mm, moduli kPa, displacements mm; K @ u is in mN.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from app.core.errors import ElastoidError
from app.core.mesh import TetMesh

# local edge order of the 10-node tetrahedron: nodes 4..9 sit on these edges
EDGES = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]])
# 4-point rule, exact for quadratics on the reference tetrahedron (weights sum to 1)
_QA, _QB = 0.5854101966249685, 0.1381966011250105
QUAD_BARY = np.array([[_QA, _QB, _QB, _QB], [_QB, _QA, _QB, _QB], [_QB, _QB, _QA, _QB], [_QB, _QB, _QB, _QA]])
QUAD_W = np.full(4, 0.25)


@dataclass(frozen=True)
class P2Space:
    """Vector P2 space on a tet mesh: nodes = vertices, then edge midpoints."""

    mesh: TetMesh
    points_mm: np.ndarray  # (N, 3)
    elems: np.ndarray  # (m, 10)
    grad_bary: np.ndarray  # (m, 4, 3): gradient of each barycentric coordinate
    volumes_mm3: np.ndarray  # (m,)
    degree: int = 2

    @property
    def n_nodes(self) -> int:
        return len(self.points_mm)

    @property
    def n_dofs(self) -> int:
        return 3 * self.n_nodes

    @property
    def labels(self) -> np.ndarray:
        return self.mesh.labels


def _bary_gradients(points: np.ndarray, tets: np.ndarray):
    p = points[tets]
    J = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=2)  # columns
    det = np.linalg.det(J)
    Jinv = np.linalg.inv(J)  # rows: gradients of lambda_1..3
    g = np.empty((len(tets), 4, 3))
    g[:, 1:] = Jinv
    g[:, 0] = -Jinv.sum(axis=1)
    return g, det / 6.0


def p2_space(mesh: TetMesh) -> P2Space:
    """Add a node at the midpoint of every edge (straight-sided elements)."""
    tets = mesh.tets
    n = mesh.n_nodes
    e = np.sort(tets[:, EDGES].reshape(-1, 2), axis=1)
    uniq, inv = np.unique(e[:, 0] * n + e[:, 1], return_inverse=True)
    ea, eb = uniq // n, uniq % n
    mids = 0.5 * (mesh.points_mm[ea] + mesh.points_mm[eb])
    elems = np.hstack([tets, n + inv.reshape(-1, 6)])
    g, vol = _bary_gradients(mesh.points_mm, tets)
    if np.any(vol <= 0):
        raise ValueError("mesh has inverted or flat tetrahedra")
    return P2Space(mesh, np.vstack([mesh.points_mm, mids]), elems, g, vol, 2)


def p1_space(mesh: TetMesh) -> P2Space:
    """The linear (4-node) space on the same mesh: for locking comparisons."""
    g, vol = _bary_gradients(mesh.points_mm, mesh.tets)
    return P2Space(mesh, mesh.points_mm, mesh.tets, g, vol, 1)


def shape_values(bary: np.ndarray, degree: int = 2) -> np.ndarray:
    """Shape functions (..., 10) at barycentric coordinates (..., 4)."""
    if degree == 1:
        return bary
    L = bary
    out = np.empty(L.shape[:-1] + (10,))
    out[..., :4] = L * (2 * L - 1)
    out[..., 4:] = 4 * L[..., EDGES[:, 0]] * L[..., EDGES[:, 1]]
    return out


def shape_gradients(bary: np.ndarray, grad_bary: np.ndarray, degree: int = 2) -> np.ndarray:
    """Gradients (m, q, nloc, 3) at barycentric points (q, 4) of elements with grad_bary (m, 4, 3)."""
    m, q = len(grad_bary), len(bary)
    if degree == 1:
        return np.broadcast_to(grad_bary[:, None], (m, q, 4, 3))
    L = bary
    out = np.empty((m, q, 10, 3))
    out[:, :, :4] = (4 * L - 1)[None, :, :, None] * grad_bary[:, None, :, :]
    i, j = EDGES[:, 0], EDGES[:, 1]
    out[:, :, 4:] = 4 * (L[:, i][None, :, :, None] * grad_bary[:, None, j, :]
                         + L[:, j][None, :, :, None] * grad_bary[:, None, i, :])
    return out


@dataclass(frozen=True)
class AffineOperator:
    """Stiffness matrices over one CSR pattern: ``data[(region, kind)]`` holds the
    value array of K for a unit coefficient (kind 'mu' or 'lam') in that region."""

    space: P2Space
    indptr: np.ndarray
    indices: np.ndarray
    data: dict  # (region index, 'mu'|'lam') -> (nnz,)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.space.n_dofs, self.space.n_dofs)

    def values(self, coeffs: dict) -> np.ndarray:
        """Value array of sum coeffs[key] * K_key."""
        out = np.zeros_like(next(iter(self.data.values())))
        for key, c in coeffs.items():
            if c != 0.0:
                out += c * self.data[key]
        return out

    def matrix(self, coeffs: dict) -> sp.csr_matrix:
        return sp.csr_matrix((self.values(coeffs), self.indices, self.indptr), shape=self.shape)


def element_positions(indptr: np.ndarray, indices: np.ndarray, elems: np.ndarray) -> np.ndarray:
    """CSR position (m, 30, 30) of every element entry (e, a i, b k) in a pattern of
    3 x 3 node blocks (dof 3 node + component, every block full, columns sorted):
    entry (3 p + i, 3 q + k) sits at indptr[3 p + i] + 3 rank(q in node p's row) + k.
    One search per node pair: a search per dof pair (9x the keys, in an array 9x
    as long) took 2.9 s of the hyperelastic solver's 3.8 s setup at paper size."""
    n_nodes = (len(indptr) - 1) // 3
    starts = indptr[0:-1:3]  # each node row's first entry (in its first dof row)
    count = (indptr[1::3] - starts) // 3  # blocks in each node row
    first = np.concatenate([[0], np.cumsum(count)])
    entry = np.repeat(starts, count) + 3 * (np.arange(first[-1]) - np.repeat(first[:-1], count))
    block_keys = np.repeat(np.arange(n_nodes, dtype=np.int64), count) * n_nodes + indices[entry] // 3
    e = np.asarray(elems, np.int64)
    keys = e[:, :, None] * n_nodes + e[:, None, :]
    found = np.searchsorted(block_keys, keys)
    if not np.array_equal(block_keys[np.minimum(found, len(block_keys) - 1)], keys):
        raise ValueError("an element's node pair is not in the pattern")
    rank = found - first[e][:, :, None]  # (m, a, b)
    base = indptr[3 * e[:, :, None] + np.arange(3)]  # (m, a, i)
    m, k = e.shape
    pos = base[:, :, :, None, None] + 3 * rank[:, :, None, :, None] + np.arange(3)
    return pos.reshape(m, 3 * k, 3 * k)


def assemble(space: P2Space, chunk: int = 4000) -> AffineOperator:
    """Assemble Kmu_r and Klam_r for every region r once.

    For basis functions N_a e_i, N_b e_j:
        Kmu[ai, bj]  = int  delta_ij grad N_a . grad N_b + d_j N_a d_i N_b
        Klam[ai, bj] = int  d_i N_a d_j N_b

    The pattern is one of full 3 x 3 node blocks; each element matrix is added
    straight into its CSR positions (element_positions), one bincount per region
    and kind (with a scatter per block component and a permutation from block to
    CSR order, assembly took 2.5-3.7 s at paper size; now 1.3-1.6 s).
    """
    elems, nloc = space.elems, space.elems.shape[1]
    N = space.n_nodes
    # block (node pair) pattern, columns sorted within a row (through a sparse matrix
    # of counts: linear time, where sorting the pairs' keys took 0.9-1.3 s at paper size)
    pairs = sp.csr_matrix((np.ones(elems.size * nloc, np.int32), (np.repeat(elems, nloc, axis=1).ravel(),
                                                                   np.tile(elems, (1, nloc)).ravel())), shape=(N, N))
    pairs.sum_duplicates()
    pairs.sort_indices()
    template = sp.bsr_matrix((np.ones((len(pairs.indices), 3, 3)), pairs.indices, pairs.indptr),
                             shape=(3 * N, 3 * N)).tocsr()
    template.sort_indices()
    nnz = len(template.indices)
    regions = [int(r) for r in np.unique(space.labels)]
    data = {(r, k): np.zeros(nnz) for r in regions for k in ("mu", "lam")}
    _add_elements(data, space, template.indptr, template.indices, None, space.labels, chunk=chunk)
    return AffineOperator(space, template.indptr.copy(), template.indices.copy(), data)


def _add_elements(data: dict, space: P2Space, indptr, indices, which: np.ndarray | None, labels: np.ndarray,
                  subtract: bool = False, chunk: int = 4000) -> None:
    """Add (or subtract) the unit element matrices of the elements ``which`` (all
    when None: taken in slices, no copies) to ``data[(labels[e], kind)]`` (value
    arrays over the CSR pattern; missing keys are made)."""
    nnz = len(indices)
    bary = QUAD_BARY  # degree 1 needs one point; four are exact too
    n = len(space.elems) if which is None else len(which)
    for s in range(0, n, chunk):
        sl = slice(s, s + chunk) if which is None else which[s : s + chunk]
        pos = element_positions(indptr, indices, space.elems[sl])  # (m, 3 nloc, 3 nloc)
        dN = shape_gradients(bary, space.grad_bary[sl], space.degree)  # (m, q, nloc, 3)
        wv = space.volumes_mm3[sl][:, None] * QUAD_W[None, :]  # (m, q)
        M = np.einsum("mq,mqak,mqbl->makbl", wv, dN, dN, optimize=True)  # int d_k N_a d_l N_b at (a k, b l)
        tr = np.einsum("makbk->mab", M)
        Kmu = np.swapaxes(M, 2, 4).copy()  # d_l N_a d_k N_b at (a k, b l)
        for k in range(3):
            Kmu[:, :, k, :, k] += tr
        lab = labels[sl]
        for r in np.unique(lab):
            sel = lab == r
            at = pos[sel].ravel()
            for kind, K in (("mu", Kmu), ("lam", M)):
                key = (int(r), kind)
                if key not in data:
                    data[key] = np.zeros(nnz)
                w = K[sel].ravel()
                if which is None or len(at) > nnz // 8:
                    data[key] += np.bincount(at, weights=-w if subtract else w, minlength=nnz)
                else:  # a few elements (relabel): only their entries, not a pass over the whole pattern
                    np.add.at(data[key], at, -w if subtract else w)


def relabel(op: AffineOperator, mesh: TetMesh) -> AffineOperator:
    """``op`` for ``mesh``: the same nodes and tets as ``op``'s mesh, with other
    regions (``mesh.labels``). Only the tets whose region changed are assembled:
    each moves from its old region's terms to its new one's. Equal to assembling
    ``mesh`` anew up to rounding; a fraction of its time when few tets change (an
    inclusion's trial sphere, diagnose.refine_inclusion)."""
    old = op.space.mesh
    if old.tets.shape != mesh.tets.shape or not (np.array_equal(old.tets, mesh.tets)
                                                 and np.array_equal(old.points_mm, mesh.points_mm)):
        raise ValueError("relabel needs the same nodes and tets")
    space = P2Space(mesh, op.space.points_mm, op.space.elems, op.space.grad_bary, op.space.volumes_mm3,
                    op.space.degree)
    changed = np.flatnonzero(old.labels != mesh.labels)
    # only the regions that lose or gain tets get new value arrays; the others are
    # shared with ``op`` (nothing changes an operator's arrays after it is made)
    touched = {int(r) for r in np.concatenate([old.labels[changed], mesh.labels[changed]])}
    data = {k: (v.copy() if k[0] in touched else v) for k, v in op.data.items()}
    _add_elements(data, space, op.indptr, op.indices, changed, old.labels, subtract=True)
    _add_elements(data, space, op.indptr, op.indices, changed, mesh.labels)
    for r in set(int(r) for r, _ in data) - set(int(r) for r in np.unique(mesh.labels)):  # regions left empty
        del data[(r, "mu")], data[(r, "lam")]
    return AffineOperator(space, op.indptr, op.indices, data)


# ---------------------------------------------------------------------------
# materials
# ---------------------------------------------------------------------------


def poisson_problem(nu) -> str | None:
    """Why ``nu`` is not a Poisson's ratio this model can take, or None: an isotropic
    solid needs -1 < nu < 0.5, and 0.5 itself (incompressible) has no Lame lambda
    for a displacement-only model."""
    try:
        v = float(nu)
    except (TypeError, ValueError):
        return f"Poisson's ratio must be a number, got {nu!r}"
    if not -1.0 < v < 0.5:
        return (f"Poisson's ratio must lie between -1 and 0.5, got {v:g}"
                + ("; for nearly incompressible tissue use e.g. 0.49 or 0.499" if v >= 0.5 else ""))
    return None


def check_poisson(nu, what: str = "nu") -> float:
    """Poisson's ratio as a float, or ElastoidError naming ``what`` (see :func:`poisson_problem`)."""
    why = poisson_problem(nu)
    if why:
        raise ElastoidError(f"{what}: {why}")
    return float(nu)


def lame(youngs_kPa: float, nu: float) -> tuple[float, float]:
    """(mu, lambda) in kPa."""
    mu = youngs_kPa / (2.0 * (1.0 + nu))
    lam = youngs_kPa * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return mu, lam


def coefficients(youngs_kPa, nu) -> dict:
    """Affine coefficients {(region, kind): value} for moduli per region (sequence)
    and one Poisson's ratio (or one per region)."""
    nus = np.broadcast_to(np.asarray(nu, float), (len(youngs_kPa),))
    out = {}
    for r, (E, v) in enumerate(zip(youngs_kPa, nus)):
        mu, lam = lame(float(E), float(v))
        out[(r, "mu")] = mu
        out[(r, "lam")] = lam
    return out


# ---------------------------------------------------------------------------
# point evaluation
# ---------------------------------------------------------------------------


def locate(space: P2Space, points: np.ndarray, tol: float = 1e-9):
    """Containing element and barycentric coordinates of each point.

    Points outside the mesh get the nearest element with clamped coordinates.
    """
    from scipy.spatial import cKDTree

    mesh = space.mesh
    P = mesh.points_mm[mesh.tets]
    cent = P.mean(axis=1)
    tree = cKDTree(cent)
    k = min(32, len(cent))
    _, cand = tree.query(points, k=k)
    cand = np.atleast_2d(cand)
    T0 = P[:, 0]
    g = space.grad_bary
    elem = np.full(len(points), -1)
    bary = np.zeros((len(points), 4))
    best = np.full(len(points), -np.inf)
    for j in range(k):
        e = cand[:, j]
        d = points - T0[e]
        l123 = np.einsum("nij,nj->ni", g[e, 1:], d)
        lam = np.column_stack([1 - l123.sum(1), l123])
        score = lam.min(axis=1)
        better = score > best
        best[better] = score[better]
        elem[better] = e[better]
        bary[better] = lam[better]
    bary = np.clip(bary, 0, None)
    bary /= bary.sum(axis=1, keepdims=True)
    return elem, bary


def interpolation_matrix(space: P2Space, points: np.ndarray) -> sp.csr_matrix:
    """Sparse (3 n_points, n_dofs) matrix giving the displacement at points, row 3p + c."""
    elem, bary = locate(space, points)
    phi = shape_values(bary, space.degree)  # (n, nloc)
    nodes = space.elems[elem]  # (n, nloc)
    n, nloc = phi.shape
    rows = (3 * np.arange(n)[:, None, None] + np.arange(3)[None, None, :]).repeat(nloc, axis=1)
    cols = 3 * nodes[:, :, None] + np.arange(3)[None, None, :]
    vals = np.repeat(phi[:, :, None], 3, axis=2)
    return sp.csr_matrix((vals.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * n, space.n_dofs))


# ---------------------------------------------------------------------------
# quadrature for loads and error norms (verification)
# ---------------------------------------------------------------------------


def collapsed_gauss(n: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Barycentric points (q, 4) and weights (sum 1) on the tetrahedron: a Gauss-Legendre
    rule on the cube mapped by the Duffy collapse (exact to degree 2n - 3 at least)."""
    x, w = np.polynomial.legendre.leggauss(n)
    x, w = 0.5 * (x + 1), 0.5 * w
    U, V, W = np.meshgrid(x, x, x, indexing="ij")
    WU, WV, WW = np.meshgrid(w, w, w, indexing="ij")
    a = U.ravel()
    b = V.ravel() * (1 - a)
    c = W.ravel() * (1 - a) * (1 - V.ravel())
    jac = (1 - U.ravel()) ** 2 * (1 - V.ravel())
    wt = (WU * WV * WW).ravel() * jac * 6.0  # reference volume 1/6 -> weights sum to 1
    bary = np.column_stack([1 - a - b - c, a, b, c])
    return bary, wt


def quadrature_points(space: P2Space, bary: np.ndarray) -> np.ndarray:
    """Physical points (m, q, 3) of barycentric points in every element."""
    P = space.mesh.points_mm[space.mesh.tets]  # (m, 4, 3)
    return np.einsum("qi,mij->mqj", bary, P)


def load_vector(space: P2Space, body_force, n: int = 4) -> np.ndarray:
    """Consistent nodal loads (n_dofs,) of a body force f(points (k, 3)) -> (k, 3)."""
    bary, wt = collapsed_gauss(n)
    X = quadrature_points(space, bary)
    f = body_force(X.reshape(-1, 3)).reshape(X.shape)
    phi = shape_values(bary, space.degree)  # (q, nloc)
    contrib = np.einsum("q,m,qa,mqc->mac", wt, space.volumes_mm3, phi, f)
    out = np.zeros((space.n_nodes, 3))
    for c in range(3):
        out[:, c] = np.bincount(space.elems.ravel(), weights=contrib[:, :, c].ravel(), minlength=space.n_nodes)
    return out.ravel()


def l2_error(space: P2Space, u: np.ndarray, exact, n: int = 4) -> float:
    """|| u_h - u_exact ||_L2 over the mesh."""
    bary, wt = collapsed_gauss(n)
    X = quadrature_points(space, bary)
    phi = shape_values(bary, space.degree)
    U = u.reshape(-1, 3)[space.elems]  # (m, nloc, 3)
    uh = np.einsum("qa,mac->mqc", phi, U)
    e = uh - exact(X.reshape(-1, 3)).reshape(X.shape)
    return float(np.sqrt(np.einsum("q,m,mqc->", wt, space.volumes_mm3, e**2)))
