"""Verification of the finite-element core against closed forms, manufactured
solutions and an independent library (scikit-fem)."""

import numpy as np
import pytest
import scipy.sparse as sp

from app.core.fem import (assemble, coefficients, element_positions, l2_error, lame, load_vector, p1_space,
                          p2_space)
from app.core.forward import Boundary, build_model
from app.core.solver import spsolve
from tests.core.helpers import cube_mesh


def _dirichlet_solve(space, op, coeffs, fixed_mask, u_fixed, f=None):
    K = op.matrix(coeffs)
    free = np.flatnonzero(~fixed_mask)
    fix = np.flatnonzero(fixed_mask)
    rhs = -(K[free][:, fix] @ u_fixed)
    if f is not None:
        rhs = rhs + f[free]
    u = np.zeros(space.n_dofs)
    u[fix] = u_fixed
    u[free] = spsolve(K[free][:, free], rhs)
    return u


def _boundary_nodes(points, size):
    return np.any(np.isclose(points, 0.0) | np.isclose(points, np.asarray(size)), axis=1)


def test_patch_test_reproduces_affine_fields_to_roundoff():
    mesh = cube_mesh(3, size=(2.0, 3.0, 1.5))
    # perturb interior vertices so elements are irregular
    rng = np.random.default_rng(0)
    inner = ~_boundary_nodes(mesh.points_mm, mesh.size_mm)
    pts = mesh.points_mm.copy()
    pts[inner] += rng.uniform(-0.12, 0.12, (inner.sum(), 3))
    mesh = type(mesh)(pts, mesh.tets, mesh.labels, mesh.region_names, mesh.size_mm, mesh.probe_rect_mm)
    space = p2_space(mesh)
    op = assemble(space)
    G = rng.normal(size=(3, 3)) * 0.01
    c = rng.normal(size=3)
    exact = (space.points_mm @ G.T + c).ravel()
    bnd = np.repeat(_boundary_nodes(space.points_mm, mesh.size_mm), 3)
    u = _dirichlet_solve(space, op, coefficients([7.0], 0.45), bnd, exact[bnd])
    assert np.abs(u - exact).max() < 1e-12 * max(1.0, np.abs(exact).max()) * 1e3


def test_stiffness_has_rigid_body_null_space_and_is_symmetric():
    space = p2_space(cube_mesh(2))
    K = assemble(space).matrix(coefficients([10.0], 0.49))
    assert abs(K - K.T).max() < 1e-10 * abs(K).max()
    x = space.points_mm
    for mode in (np.tile([1.0, 0, 0], (len(x), 1)), np.cross([0, 0, 1.0], x), np.cross([1.0, 0, 0], x)):
        assert np.abs(K @ mode.ravel()).max() < 1e-10 * abs(K).max()


def test_uniaxial_compression_matches_closed_form():
    """Sliding bottom, frictionless rigid top pressed by d: F = E A d / H, u_x = nu eps x."""
    size = (20.0, 30.0, 40.0)
    mesh = cube_mesh(3, size=size, probe_rect=(0.0, 20.0, 0.0, 30.0))
    E, nu, d = 12.0, 0.45, 0.8
    model = build_model(mesh, Boundary(bottom="sliding", probe="slip"))
    u, F_per_mm = model.solve([E], nu)
    F_exact = E * size[0] * size[1] / size[2] * 1e-3  # kPa * mm^2 / mm -> N per mm of travel
    assert F_per_mm == pytest.approx(F_exact, rel=1e-10)
    eps = 1.0 / size[2]
    U = u.reshape(-1, 3)
    x = model.space.points_mm
    assert np.allclose(U[:, 2], -eps * x[:, 2], atol=1e-11)
    assert np.allclose(U[:, 0], nu * eps * (x[:, 0] - size[0] / 2), atol=1e-11)
    assert d * F_per_mm == pytest.approx(d * F_exact, rel=1e-10)


def _divergence_free_field():
    """u = curl(0, 0, psi) with psi = (sin pi x sin pi y sin pi z)^2: zero on the cube's
    boundary, divergence free, so the body force -mu Lap u does not depend on lambda."""

    def psi_grad(X):
        s = np.sin(np.pi * X)
        cth = np.cos(np.pi * X)
        S = s.prod(axis=1)
        gx = 2 * S * np.pi * cth[:, 0] * s[:, 1] * s[:, 2]
        gy = 2 * S * np.pi * s[:, 0] * cth[:, 1] * s[:, 2]
        return gx, gy

    def u(X):
        gx, gy = psi_grad(X)
        return np.column_stack([gy, -gx, np.zeros(len(X))])

    def lap_u(X, h=1e-3):
        out = -30 * u(X) * 3
        for k in range(3):
            e = np.zeros(3)
            e[k] = h
            out = out - u(X + 2 * e) + 16 * u(X + e) + 16 * u(X - e) - u(X - 2 * e)
        return out / (12 * h * h)

    return u, lap_u


def _manufactured_errors(ns, nu, space_fn):
    u_exact, lap_u = _divergence_free_field()
    E = 1.0
    mu, _ = lame(E, nu)
    errs = []
    for n in ns:
        mesh = cube_mesh(n)
        space = space_fn(mesh)
        op = assemble(space)
        f = load_vector(space, lambda X: -mu * lap_u(X))
        bnd = np.repeat(_boundary_nodes(space.points_mm, mesh.size_mm), 3)
        u = _dirichlet_solve(space, op, coefficients([E], nu), bnd, np.zeros(bnd.sum()), f)
        errs.append(l2_error(space, u, u_exact) / l2_error(space, np.zeros_like(u), u_exact))
    return np.array(errs)


def test_manufactured_solution_converges_at_third_order():
    errs = _manufactured_errors([2, 4, 8], 0.3, p2_space)
    rates = np.log2(errs[:-1] / errs[1:])
    assert errs[-1] < 0.02, errs
    assert rates[-1] > 2.7, f"L2 rates {rates}"


def test_quadratic_elements_do_not_lock_when_nearly_incompressible():
    """The same divergence-free solution at nu = 0.4999: linear tets lock (they
    return almost no displacement, and refining does not help), quadratic tets
    keep converging at better than second order."""
    p1 = _manufactured_errors([4, 8], 0.4999, p1_space)
    p2 = _manufactured_errors([4, 8], 0.4999, p2_space)
    assert p1.min() > 0.95, p1  # locked: ~100% error at every refinement
    assert p2[1] < 0.1, p2
    assert np.log2(p2[0] / p2[1]) > 1.8, p2
    # at the model's default nu = 0.49 the P2 error is within a few % on the finer mesh
    assert _manufactured_errors([8], 0.49, p2_space)[0] < 0.05


def test_assembly_matches_scikit_fem():
    """Energy of P2 fields and the stiffness itself agree with scikit-fem on the same mesh."""
    from skfem import Basis, ElementTetP2, ElementVector, MeshTet, asm
    from skfem.models.elasticity import linear_elasticity

    mesh = cube_mesh(2, size=(1.0, 2.0, 1.5))
    space = p2_space(mesh)
    E, nu = 5.0, 0.49
    K = assemble(space).matrix(coefficients([E], nu))
    sk_mesh = MeshTet(mesh.points_mm.T.copy(), mesh.tets.T.copy())
    basis = Basis(sk_mesh, ElementVector(ElementTetP2()), intorder=2)
    mu, lam = lame(E, nu)
    Ksk = asm(linear_elasticity(lam, mu), basis)
    rng = np.random.default_rng(1)
    for _ in range(3):
        C = rng.normal(size=(3, 10))

        def field(X):  # a random quadratic vector field, exactly representable in P2
            x, y, z = X
            mon = np.array([np.ones_like(x), x, y, z, x * x, y * y, z * z, x * y, y * z, x * z])
            return np.einsum("cm,m...->c...", C, mon)

        comp = np.empty(basis.N, int)
        for c in range(3):
            comp[basis.nodal_dofs[c]] = c
            comp[basis.edge_dofs[c]] = c
        u_sk = field(basis.doflocs)[comp, np.arange(basis.N)]
        X = space.points_mm
        u_ours = field(X.T).T.ravel()
        e_ours = u_ours @ (K @ u_ours)
        e_sk = u_sk @ (Ksk @ u_sk)
        assert e_ours == pytest.approx(e_sk, rel=1e-9)
    assert sp.linalg.norm(Ksk) == pytest.approx(sp.linalg.norm(K), rel=1e-9)


def test_element_entries_find_their_csr_positions_node_block_by_node_block():
    fe = build_model(cube_mesh(2, size=(10.0, 10.0, 8.0), probe_rect=(2.5, 7.5, 2.5, 7.5)))
    op, elems = fe.op, fe.space.elems
    pos = element_positions(op.indptr, op.indices, elems)
    # the plain search, dof pair by dof pair
    n = fe.space.n_dofs
    rows = np.repeat(np.arange(n), np.diff(op.indptr))
    dofs = (3 * elems[:, :, None] + np.arange(3)).reshape(len(elems), -1)
    keys = dofs[:, :, None].astype(np.int64) * n + dofs[:, None, :]
    assert np.array_equal(pos, np.searchsorted(rows.astype(np.int64) * n + op.indices, keys))
    assert np.array_equal(rows[pos], np.broadcast_to(dofs[:, :, None], pos.shape))
    assert np.array_equal(op.indices[pos], np.broadcast_to(dofs[:, None, :], pos.shape))
    # a node pair the pattern lacks is an error, not a wrong position
    other = elems.copy()
    neighbours = set(np.unique(elems[np.any(elems == elems[0, 0], axis=1)]))  # of node elems[0, 0]
    far = [q for q in range(fe.space.n_nodes) if q not in neighbours]
    other[0, 1] = far[0]
    with pytest.raises(ValueError, match="not in the pattern"):
        element_positions(op.indptr, op.indices, other)


def test_relabelled_operator_equals_the_relabelled_mesh_assembled_anew():
    """relabel moves only the tets whose region changed; the result is the
    assembly of the relabelled mesh, region by region and kind by kind (a third
    region made, one region emptied), and it refuses another mesh."""
    from dataclasses import replace

    from app.core.fem import relabel

    mesh = cube_mesh(3, size=(10.0, 10.0, 8.0))
    centroids = mesh.points_mm[mesh.tets].mean(axis=1)
    labels = (centroids[:, 0] > 5.0).astype(mesh.labels.dtype)
    two = replace(mesh, labels=labels, region_names=("B", "A"))
    op = assemble(p2_space(two))
    ball = np.linalg.norm(centroids - [4.0, 5.0, 4.0], axis=1) < 3.0
    three = replace(two, labels=np.where(ball, 2, labels).astype(labels.dtype), region_names=("B", "A", "I"))
    assert 0 < ball.sum() < len(ball) and np.any(ball & (labels == 0)) and np.any(ball & (labels == 1))
    new, ref = relabel(op, three), assemble(p2_space(three))
    assert set(new.data) == set(ref.data) == {(r, k) for r in range(3) for k in ("mu", "lam")}
    scale = max(np.abs(v).max() for v in ref.data.values())
    for key in ref.data:
        assert np.abs(new.data[key] - ref.data[key]).max() < 1e-12 * scale, key
    assert np.array_equal(new.indptr, ref.indptr) and np.array_equal(new.indices, ref.indices)
    assert np.array_equal(new.space.labels, three.labels) and new.space.mesh is three
    assert np.array_equal(op.space.labels, labels)  # the operator relabelled is left as it was
    # a few tets of A alone (an inclusion's trial sphere): B's arrays are shared, not
    # copied, and only the moved tets' entries are touched; the result is still the
    # assembly anew, and the operator relabelled keeps its values
    before = {k: v.copy() for k, v in op.data.items()}
    dist = np.linalg.norm(centroids - [8.0, 5.0, 4.0], axis=1)
    few = (labels == 1) & (dist <= np.sort(dist[labels == 1])[3])
    small = replace(two, labels=np.where(few, 2, labels).astype(labels.dtype), region_names=("B", "A", "I"))
    new, ref = relabel(op, small), assemble(p2_space(small))
    assert few.sum() == 4 and new.data[(0, "mu")] is op.data[(0, "mu")]  # B keeps its tets: shared
    assert new.data[(1, "mu")] is not op.data[(1, "mu")]
    for key in ref.data:
        assert np.abs(new.data[key] - ref.data[key]).max() < 1e-12 * scale, key
    assert all(np.array_equal(op.data[k], v) for k, v in before.items())
    emptied = relabel(op, replace(two, labels=np.ones_like(labels)))
    assert set(emptied.data) == {(1, "mu"), (1, "lam")}
    ones = assemble(p2_space(replace(two, labels=np.ones_like(labels))))
    assert np.abs(emptied.data[(1, "mu")] - ones.data[(1, "mu")]).max() < 1e-12 * scale
    with pytest.raises(ValueError, match="same nodes and tets"):
        relabel(op, cube_mesh(2, size=(10.0, 10.0, 8.0)))
