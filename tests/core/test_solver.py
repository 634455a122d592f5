"""The sparse direct solvers: PARDISO when MKL is there, SuperLU otherwise
(Apple silicon, some lab PCs). Both paths must give the same answers, including
the numeric-only refactorization the hyperelastic solver uses."""

import numpy as np
import pytest
import scipy.sparse as sp

import app.core.solver as solver


def _spd(n=300, seed=0):
    A = sp.random(n, n, 0.03, random_state=seed)
    return (A @ A.T + 4.0 * sp.eye(n)).tocsr()


@pytest.mark.parametrize("pardiso", [True, False], ids=["pardiso", "superlu"])
@pytest.mark.parametrize("single", [False, True])
def test_symmetric_factor_solves_and_refactors(monkeypatch, pardiso, single):
    if pardiso and not solver.HAVE_PARDISO:
        pytest.fail("MKL PARDISO is expected on this platform (x86_64 with mkl)")
    monkeypatch.setattr(solver, "HAVE_PARDISO", pardiso)
    A = _spd()
    U = sp.triu(A, format="csr")
    U.sort_indices()
    b = np.linspace(-1.0, 1.0, A.shape[0])
    tol = 1e-4 if (single and pardiso) else 1e-10
    f = solver.SymmetricFactor(U, single=single)
    x = f.solve(b)
    assert np.abs(A @ x - b).max() / np.abs(b).max() < tol
    f.refactor(3.0 * U.data)  # same pattern, new values
    x = f.solve(b)
    assert np.abs(3.0 * (A @ x) - b).max() / np.abs(b).max() < tol
    f.free()


@pytest.mark.parametrize("pardiso", [True, False], ids=["pardiso", "superlu"])
def test_factorized_solves_many_right_hand_sides(monkeypatch, pardiso):
    monkeypatch.setattr(solver, "HAVE_PARDISO", pardiso and solver.HAVE_PARDISO)
    A = _spd(seed=1)
    B = np.random.default_rng(0).standard_normal((A.shape[0], 3))
    X = solver.spsolve(A, B)
    assert np.abs(A @ X - B).max() < 1e-10


@pytest.mark.parametrize("pardiso", [True, False], ids=["pardiso", "superlu"])
def test_symmetric_factor_reports_the_inertia_of_an_indefinite_matrix(monkeypatch, pardiso):
    """The hyperelastic iteration keeps tangents with negative eigenvalues out (their
    Newton step need not lower the energy): PARDISO's count must be right. Without
    MKL PARDISO (SuperLU) the inertia is unknown and says so (None): the iteration
    then relies on its descent check alone."""
    if pardiso and not solver.HAVE_PARDISO:
        pytest.fail("MKL PARDISO is expected on this platform (x86_64 with mkl)")
    monkeypatch.setattr(solver, "HAVE_PARDISO", pardiso)
    rng = np.random.default_rng(0)
    n = 60
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    for n_neg in (0, 1, 3):
        eig = np.concatenate([-rng.uniform(0.5, 2.0, n_neg), rng.uniform(0.5, 2.0, n - n_neg)])
        A = (Q * eig) @ Q.T
        f = solver.SymmetricFactor(sp.csr_matrix(np.triu(A)), single=False)
        assert f.negative_eigenvalues == (n_neg if pardiso else None)
        b = rng.normal(size=n)
        assert np.allclose(A @ f.solve(b), b, atol=1e-8)
        f.free()


def test_a_cholesky_factor_reports_a_matrix_that_is_not_positive_definite():
    """The hyperelastic iteration factorizes its tangents by Cholesky (faster than
    LDL^T) and learns from a failed factorization that a tangent is not positive
    definite: the failure is reported, not raised, solving with it is refused,
    and the same factor serves again once refactorized with definite values."""
    from app.core.errors import ElastoidError

    if not solver.HAVE_PARDISO:
        pytest.fail("MKL PARDISO is expected on this platform (x86_64 with mkl)")
    rng = np.random.default_rng(1)
    n = 60
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    eig = rng.uniform(0.5, 2.0, n)
    spd = (Q * eig) @ Q.T
    indefinite = spd - 0.6 * np.eye(n)  # the smallest eigenvalues turn negative
    assert np.linalg.eigvalsh(indefinite).min() < 0
    b = rng.normal(size=n)
    for single in (False, True):
        f = solver.SymmetricFactor(sp.csr_matrix(np.triu(indefinite)), single=single, definite=True)
        assert f.positive_definite is False
        with pytest.raises(ElastoidError, match="not positive definite"):
            f.solve(b)
        f.refactor(sp.csr_matrix(np.triu(spd)).data)
        assert f.positive_definite is True
        assert np.allclose(spd @ f.solve(b), b, atol=1e-8 if not single else 1e-4)
        f.free()


def test_factors_sharing_one_analysis_solve_independently():
    """Factors of one pattern share one PARDISO analysis (the hyperelastic model
    keeps one per load step): each solves its own matrix, freeing one leaves the
    others intact and frees its slot, and a factor beyond the slots gets an
    analysis of its own."""
    if not solver.HAVE_PARDISO:
        pytest.fail("MKL PARDISO is expected on this platform (x86_64 with mkl)")
    A = _spd(seed=2)
    U = sp.triu(A, format="csr")
    U.sort_indices()
    b = np.linspace(-1.0, 1.0, A.shape[0])
    first = solver.SymmetricFactor(U, single=False, definite=True, slots=3)
    scaled = [solver.SymmetricFactor(sp.csr_matrix((k * U.data, U.indices, U.indptr), shape=U.shape),
                                     single=False, definite=True, share=first) for k in (2.0, 3.0)]
    assert all(f._handle is first._handle for f in scaled)
    beyond = solver.SymmetricFactor(U, single=False, definite=True, share=first)  # the 4th of 3 slots
    assert beyond._handle is not first._handle
    for k, f in zip((1.0, 2.0, 3.0, 1.0), [first, *scaled, beyond]):
        assert np.abs(k * (A @ f.solve(b)) - b).max() < 1e-10
    first.free()  # its factor only: the analysis stays with the others
    assert np.abs(3.0 * (A @ scaled[1].solve(b)) - b).max() < 1e-10
    again = solver.SymmetricFactor(sp.csr_matrix((5.0 * U.data, U.indices, U.indptr), shape=U.shape),
                                   single=False, definite=True, share=scaled[0])
    assert again._handle is scaled[0]._handle and again.mnum == 1  # the slot freed
    assert np.abs(5.0 * (A @ again.solve(b)) - b).max() < 1e-10
    assert np.abs(2.0 * (A @ scaled[0].solve(b)) - b).max() < 1e-10
    for f in (*scaled, again, beyond):
        f.free()


@pytest.mark.parametrize("pardiso", [True, False], ids=["pardiso", "superlu"])
def test_the_reduced_models_preconditioner(monkeypatch, pardiso):
    """preconditioner(): a factor of the whole SPD matrix (given in full, not as
    its upper triangle), single precision with PARDISO (residual to single
    precision's accuracy), SuperLU's double precision without it; freed on
    request; a matrix that is not positive definite is refused in words."""
    from app.core.errors import ElastoidError

    if pardiso and not solver.HAVE_PARDISO:
        pytest.fail("MKL PARDISO is expected on this platform (x86_64 with mkl)")
    monkeypatch.setattr(solver, "HAVE_PARDISO", pardiso)
    A = _spd()
    b = np.random.default_rng(2).normal(size=A.shape[0])
    p = solver.preconditioner(A)
    x = p.solve(b)
    assert x.dtype == np.float64
    rel = np.linalg.norm(A @ x - b) / np.linalg.norm(b)
    assert rel < (1e-5 if pardiso else 1e-12) and (rel > 1e-12) == pardiso  # single precision only with MKL
    assert p.alive
    p.free()
    assert not p.alive
    if pardiso:  # SuperLU factorizes an indefinite matrix without complaint
        with pytest.raises(ElastoidError, match=r"stiffness matrix \(300 unknowns\) is not positive definite"):
            solver.preconditioner((A - 40.0 * sp.eye(A.shape[0])).tocsr())
