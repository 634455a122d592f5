"""Sparse direct solves of symmetric positive definite systems: MKL PARDISO
(through pypardiso, Cholesky, METIS ordering) when present, else SuperLU.
"""

from __future__ import annotations

import os

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

try:  # MKL is not available on every platform (e.g. Apple silicon)
    import pypardiso

    HAVE_PARDISO = True
except Exception:  # pragma: no cover - depends on the platform
    pypardiso = None
    HAVE_PARDISO = False


def _remember_mkl_path() -> None:
    """Every new pypardiso solver looks for MKL's library again: find_library, and
    when that fails (a pip-installed MKL) a recursive glob of the environment's
    lib folders, 0.6 s per solver here (a diagnosis makes a dozen). The first
    solver's find is kept in PYPARDISO_MKL_RT, pypardiso's own override."""
    if not HAVE_PARDISO or os.environ.get("PYPARDISO_MKL_RT"):
        return
    try:  # the solver pypardiso made at import (it has searched already), else a new one
        solver = getattr(getattr(pypardiso, "scipy_aliases", None), "pypardiso_solver", None)
        path = getattr((solver or pypardiso.PyPardisoSolver()).libmkl, "_name", None)
    except Exception:  # pragma: no cover - MKL missing: pypardiso's own error comes later
        return
    if path and os.path.isfile(path):
        os.environ["PYPARDISO_MKL_RT"] = path


_remember_mkl_path()


_POOLS = None


def single_threaded_blas():
    """Context capping numpy's BLAS (OpenBLAS) at one thread: in these small products
    its idle threads only spin and steal the cores. MKL, which here serves only
    PARDISO, keeps its threads (capping it too made the reduced-basis training's
    back-substitutions 2x slower; with OpenBLAS capped, warm hyperelastic solves
    on the demo took 1.35 and 1.65 s against 1.69 and 1.70 s, medians of 6 in
    two runs each). The controller is built once: building it scans the process."""
    global _POOLS
    if _POOLS is None:
        from threadpoolctl import ThreadpoolController

        _POOLS = ThreadpoolController().select(internal_api=["openblas", "blis"])
    return _POOLS.limit(limits=1)


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
            self._U.data = np.ascontiguousarray(self._U.data, np.float64)
            # PARDISO's one-based index arrays, kept: pypardiso's own solve() converts
            # them and compares the whole matrix with the factorized one on every
            # call, which cost several times the back-substitution itself
            self._ia = (self._U.indptr + 1).astype(np.int32)
            self._ja = (self._U.indices + 1).astype(np.int32)
            self._s = pypardiso.PyPardisoSolver(mtype=2)
            _configure(self._s)  # Cholesky of an SPD matrix is backward stable: no refinement
            try:
                self._s.factorize(self._U)
            except pypardiso.pardiso_wrapper.PyPardisoError as exc:
                from app.core.errors import ElastoidError

                raise ElastoidError(f"the sparse solver failed on {A.shape[0]:,} unknowns ({exc}); error -2 means "
                                    "not enough memory: use a coarser mesh") from None
        else:
            self._lu = spla.splu(A.tocsc(), permc_spec="MMD_AT_PLUS_A")

    def solve(self, b: np.ndarray) -> np.ndarray:
        b = np.asarray(b, float)
        if HAVE_PARDISO:
            if b.shape[0] != self.shape[0]:
                raise ValueError(f"right-hand side of {b.shape[0]} rows for a {self.shape[0]}-row matrix")
            return _pardiso(self._s, 2, 33, self._U.data, self._ia, self._ja, b)
        return self._lu.solve(b)

    def free(self) -> None:
        """Release the factor now (MKL's memory is not released by garbage
        collection of the Python object alone: :meth:`__del__` calls this)."""
        if HAVE_PARDISO and getattr(self, "_s", None) is not None:
            s, self._s = self._s, None
            s.free_memory(everything=True)

    def __del__(self):
        try:
            self.free()
        except Exception:  # interpreter shutdown: modules may be gone
            pass


def _configure(solver, single: bool = False) -> None:
    """Our PARDISO parameters on a pypardiso solver: given explicitly (MKL's
    defaults, iparm[0] = 0, add two refinement steps to every solve), METIS
    ordering, one-based indices, no iterative refinement, double or single precision."""
    ip = solver.iparm
    ip[:] = 0
    ip[0] = 1  # iparm given
    ip[1] = 2  # METIS nested dissection
    ip[34] = 0  # one-based indices
    ip[27] = 1 if single else 0


def _pardiso(s, mtype: int, phase: int, data: np.ndarray, ia: np.ndarray, ja: np.ndarray,
             b: np.ndarray) -> np.ndarray:
    """One PARDISO call (11 analysis, 22 numeric factorization, 33 solve) on the
    handle of pypardiso solver ``s``, for one right-hand side or the columns of
    ``b``; ``data`` is in the factor's precision."""
    import ctypes as ct

    from app.core.errors import ElastoidError

    b = np.asfortranarray(b, data.dtype)
    x = np.zeros_like(b, order="F")
    err = ct.c_int32(0)
    i32 = ct.POINTER(ct.c_int32)
    nrhs = 1 if b.ndim == 1 else b.shape[1]
    s._mkl_pardiso.argtypes = None  # pypardiso sets double-only argtypes on the shared function
    s._mkl_pardiso(s.pt.ctypes.data_as(ct.POINTER(s._pt_type[0])), ct.byref(ct.c_int32(1)), ct.byref(ct.c_int32(1)),
                   ct.byref(ct.c_int32(mtype)), ct.byref(ct.c_int32(phase)), ct.byref(ct.c_int32(len(ia) - 1)),
                   data.ctypes.data_as(ct.c_void_p), ia.ctypes.data_as(i32), ja.ctypes.data_as(i32),
                   s.perm.ctypes.data_as(i32), ct.byref(ct.c_int32(nrhs)), s.iparm.ctypes.data_as(i32),
                   ct.byref(ct.c_int32(0)), b.ctypes.data_as(ct.c_void_p), x.ctypes.data_as(ct.c_void_p),
                   ct.byref(err))
    if err.value != 0:
        raise ElastoidError(f"PARDISO failed (error {err.value})")
    return np.ascontiguousarray(x)


class SymmetricFactor:
    """Cholesky factor of an SPD matrix with a fixed sparsity pattern, refactorized
    in place for new values (the ordering and symbolic analysis are done once).

    MKL PARDISO through pypardiso's library handle, in single precision by
    default: it serves as the fixed iteration matrix of a modified Newton method,
    where half the memory and time matter and its 1e-6 accuracy does not. Without
    MKL it falls back to :class:`app.core.solver.Factorized` (double precision).
    """

    def __init__(self, upper: sp.csr_matrix, single: bool = True, definite: bool = False,
                 ordering: np.ndarray | None = None):
        """``ordering``: the fill-reducing permutation of an earlier factor of a matrix
        with the same pattern (its :attr:`ordering`), which skips METIS (about half
        of the analysis)."""
        self.n = upper.shape[0]
        self._fallback = None
        self.ordering = None
        if not HAVE_PARDISO:
            self._upper = sp.csr_matrix(upper)
            self._fallback = Factorized(self._upper + sp.triu(self._upper, 1).T)
            return
        import pypardiso

        self.mtype = 2 if definite else -2  # -2: symmetric indefinite (Bunch-Kaufman pivoting)
        self._s = pypardiso.PyPardisoSolver(mtype=self.mtype)
        _configure(self._s, single)
        self._s.iparm[9] = 8  # pivot perturbation 1e-8
        if ordering is not None and len(ordering) == self.n:
            self._s.iparm[4] = 1  # the permutation is given
            self._s.perm = np.ascontiguousarray(ordering, np.int32)
        else:
            self._s.iparm[4] = 2  # return the permutation METIS computed
            self._s.perm = np.zeros(self.n, np.int32)
        self.dtype = np.float32 if single else np.float64
        self._ia = (upper.indptr + 1).astype(np.int32)
        self._ja = (upper.indices + 1).astype(np.int32)
        self._data = upper.data.astype(self.dtype)
        self._call(11, np.zeros(self.n, self.dtype))
        self.ordering = self._s.perm.copy()
        self._call(22, np.zeros(self.n, self.dtype))

    def _call(self, phase: int, b: np.ndarray) -> np.ndarray:
        return _pardiso(self._s, self.mtype, phase, self._data, self._ia, self._ja, b)

    def refactor(self, upper_data: np.ndarray) -> None:
        """New values on the same pattern: numeric factorization only."""
        if self._fallback is not None:  # SuperLU has no numeric-only refactorization: factorize anew
            self._fallback.free()
            U = sp.csr_matrix((np.asarray(upper_data, float), self._upper.indices, self._upper.indptr),
                              shape=self._upper.shape)
            self._fallback = Factorized(U + sp.triu(U, 1).T)
            return
        self._data = np.ascontiguousarray(upper_data, self.dtype)
        self._call(22, np.zeros(self.n, self.dtype))

    @property
    def negative_eigenvalues(self) -> int | None:
        """Number of negative eigenvalues of the last factorized matrix (its inertia,
        from PARDISO's Bunch-Kaufman factorization), or None when unknown (SuperLU)."""
        if self._fallback is not None or self.mtype != -2:
            return None
        return int(self._s.iparm[22])

    def solve(self, b: np.ndarray) -> np.ndarray:
        if self._fallback is not None:
            return self._fallback.solve(b)
        return self._call(33, np.ascontiguousarray(b, self.dtype)).astype(np.float64)

    def free(self) -> None:
        if self._fallback is not None:
            self._fallback.free()
        elif getattr(self, "_s", None) is not None:
            self._call(-1, np.zeros(self.n, self.dtype))
            self._s = None

    def __del__(self):  # MKL's memory outlives the Python object unless released
        try:
            self.free()
        except Exception:  # interpreter shutdown: modules may be gone
            pass


def spsolve(A: sp.spmatrix, b: np.ndarray) -> np.ndarray:
    f = Factorized(A)
    try:
        return f.solve(b)
    finally:
        f.free()
