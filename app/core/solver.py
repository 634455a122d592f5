"""Sparse direct solves of symmetric positive definite systems: MKL PARDISO
(through pypardiso, Cholesky, METIS ordering) when present, else SuperLU.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

try:  # MKL is not available on every platform (e.g. Apple silicon)
    import pypardiso

    HAVE_PARDISO = True
except Exception:  # pragma: no cover - depends on the platform
    pypardiso = None
    HAVE_PARDISO = False


def backend_name() -> str:
    return "pardiso" if HAVE_PARDISO else "superlu"


class Factorized:
    """A factorized SPD sparse matrix: ``solve(b)`` for one or many right-hand sides."""

    def __init__(self, A: sp.spmatrix):
        A = sp.csr_matrix(A)
        self.shape = A.shape
        if HAVE_PARDISO:
            # real symmetric positive definite: PARDISO reads the upper triangle
            self._U = sp.triu(A, format="csr")
            self._U.sort_indices()
            self._s = pypardiso.PyPardisoSolver(mtype=2)
            self._s.factorize(self._U)
        else:
            self._lu = spla.splu(A.tocsc(), permc_spec="MMD_AT_PLUS_A")

    def solve(self, b: np.ndarray) -> np.ndarray:
        b = np.asarray(b, float)
        if HAVE_PARDISO:
            return self._s.solve(self._U, b)
        return self._lu.solve(b)

    def free(self) -> None:
        if HAVE_PARDISO:
            self._s.free_memory(everything=True)


def spsolve(A: sp.spmatrix, b: np.ndarray) -> np.ndarray:
    f = Factorized(A)
    try:
        return f.solve(b)
    finally:
        f.free()
