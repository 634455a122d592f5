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
