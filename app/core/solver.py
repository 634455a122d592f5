"""Sparse direct solves of symmetric positive definite systems: MKL PARDISO
(through pypardiso, Cholesky, METIS ordering) when present, else SuperLU.
"""

from __future__ import annotations

import os

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from app.core.errors import ElastoidError

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

    @property
    def alive(self) -> bool:
        """Whether it can still solve (not freed)."""
        return getattr(self, "_s" if HAVE_PARDISO else "_lu", None) is not None

    def free(self) -> None:
        """Release the factor now (MKL's memory is not released by garbage
        collection of the Python object alone: :meth:`__del__` calls this)."""
        if HAVE_PARDISO and getattr(self, "_s", None) is not None:
            s, self._s = self._s, None
            s.free_memory(everything=True)
        elif not HAVE_PARDISO:
            self._lu = None

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
             b: np.ndarray, maxfct: int = 1, mnum: int = 1) -> np.ndarray:
    """One PARDISO call (11 analysis, 22 numeric factorization, 33 solve, 0 release
    factor ``mnum``, -1 release all) on the handle of pypardiso solver ``s``, for
    one right-hand side or the columns of ``b``; ``data`` is in the factor's
    precision. ``maxfct``: how many factors share the handle's analysis (the same
    on every call); ``mnum``: which of them (1-based)."""
    import ctypes as ct

    b = np.asfortranarray(b, data.dtype)
    x = np.zeros_like(b, order="F")
    err = ct.c_int32(0)
    i32 = ct.POINTER(ct.c_int32)
    nrhs = 1 if b.ndim == 1 else b.shape[1]
    s._mkl_pardiso.argtypes = None  # pypardiso sets double-only argtypes on the shared function
    s._mkl_pardiso(s.pt.ctypes.data_as(ct.POINTER(s._pt_type[0])), ct.byref(ct.c_int32(maxfct)),
                   ct.byref(ct.c_int32(mnum)),
                   ct.byref(ct.c_int32(mtype)), ct.byref(ct.c_int32(phase)), ct.byref(ct.c_int32(len(ia) - 1)),
                   data.ctypes.data_as(ct.c_void_p), ia.ctypes.data_as(i32), ja.ctypes.data_as(i32),
                   s.perm.ctypes.data_as(i32), ct.byref(ct.c_int32(nrhs)), s.iparm.ctypes.data_as(i32),
                   ct.byref(ct.c_int32(0)), b.ctypes.data_as(ct.c_void_p), x.ctypes.data_as(ct.c_void_p),
                   ct.byref(err))
    if err.value != 0:
        raise PardisoFailed(err.value)
    return np.ascontiguousarray(x)


class PardisoFailed(ElastoidError):
    """A PARDISO call returned an error code (-4: a zero or negative pivot, e.g. a
    Cholesky factorization of a matrix that is not positive definite)."""

    def __init__(self, code: int):
        super().__init__(f"PARDISO failed (error {code})")
        self.code = code


class _Handle:
    """A PARDISO handle with the analysis of one sparsity pattern, and the factor
    numbers (``mnum``) of its ``maxfct`` still free."""

    def __init__(self, solver, maxfct: int):
        self.s, self.maxfct = solver, maxfct
        self.free_slots = list(range(maxfct, 1, -1))  # 1 is the analysing factor's
        self.users = 1


class SymmetricFactor:
    """Factor of a symmetric matrix with a fixed sparsity pattern, refactorized
    in place for new values (the ordering and symbolic analysis are done once):
    Cholesky with ``definite`` (a matrix that is not positive definite is reported
    by :attr:`positive_definite`, and cannot be solved with), else LDL^T with
    Bunch-Kaufman pivoting, whose inertia :attr:`negative_eigenvalues` gives.
    Cholesky took 10% less time to factorize and 15% less to back-substitute on
    the demo's tangent (52,173 unknowns, single precision: 0.69 against 0.77 s,
    25 against 30 ms).

    Factors of one pattern can share one analysis (``share``, up to ``slots`` of
    them): a new factor then costs a numeric factorization only, and holds no
    copy of the analysis (on the demo's tangent about 0.4 s and 70 MB each).

    MKL PARDISO through pypardiso's library handle, in single precision by
    default: it serves as the fixed iteration matrix of a modified Newton method,
    where half the memory and time matter and its 1e-6 accuracy does not. Without
    MKL it falls back to :class:`app.core.solver.Factorized` (double precision).
    """

    def __init__(self, upper: sp.csr_matrix, single: bool = True, definite: bool = False,
                 ordering: np.ndarray | None = None, share: SymmetricFactor | None = None, slots: int = 1):
        """``ordering``: the fill-reducing permutation of an earlier factor of a matrix
        with the same pattern (its :attr:`ordering`), which skips METIS (about half
        of the analysis). ``share``: a live factor of a matrix with the same pattern,
        precision and kind whose analysis this one uses when it has a slot free
        (else this one analyses anew). ``slots``: how many factors, this one
        included, may share this one's analysis."""
        self.n = upper.shape[0]
        self._fallback = None
        self._handle = None
        self.ordering = None
        if not HAVE_PARDISO:
            self._upper = sp.csr_matrix(upper)
            self._fallback = Factorized(self._upper + sp.triu(self._upper, 1).T)
            return
        import pypardiso

        self.mtype = 2 if definite else -2  # -2: symmetric indefinite (Bunch-Kaufman pivoting)
        self.dtype = np.float32 if single else np.float64
        self._data = upper.data.astype(self.dtype)
        h = getattr(share, "_handle", None)
        if h is not None and h.free_slots and (share.n, share.mtype, share.dtype) == (self.n, self.mtype, self.dtype):
            self._handle, self.mnum = h, h.free_slots.pop()
            h.users += 1
            self._ia, self._ja, self.ordering = share._ia, share._ja, share.ordering
            self._numeric()
            return
        s = pypardiso.PyPardisoSolver(mtype=self.mtype)
        _configure(s, single)
        s.iparm[9] = 8  # pivot perturbation 1e-8
        if ordering is not None and len(ordering) == self.n:
            s.iparm[4] = 1  # the permutation is given
            s.perm = np.ascontiguousarray(ordering, np.int32)
        else:
            s.iparm[4] = 2  # return the permutation METIS computed
            s.perm = np.zeros(self.n, np.int32)
        self._handle, self.mnum = _Handle(s, max(1, int(slots))), 1
        self._ia = (upper.indptr + 1).astype(np.int32)
        self._ja = (upper.indices + 1).astype(np.int32)
        self._call(11, np.zeros(self.n, self.dtype))
        self.ordering = s.perm.copy()
        self._numeric()

    def _call(self, phase: int, b: np.ndarray) -> np.ndarray:
        h = self._handle
        return _pardiso(h.s, self.mtype, phase, self._data, self._ia, self._ja, b, h.maxfct, self.mnum)

    def _numeric(self) -> None:
        """The numeric factorization; a Cholesky one (``definite``) of a matrix that
        is not positive definite fails on a negative pivot, which is recorded
        (:attr:`positive_definite`) rather than raised."""
        self._definite = True
        try:
            self._call(22, np.zeros(self.n, self.dtype))
        except PardisoFailed as exc:
            if self.mtype != 2 or exc.code != -4:
                raise
            self._definite = False
        self._negative = int(self._handle.s.iparm[22]) if self.mtype == -2 else 0  # the shared iparm changes

    def refactor(self, upper_data: np.ndarray) -> None:
        """New values on the same pattern: numeric factorization only."""
        if self._fallback is not None:  # SuperLU has no numeric-only refactorization: factorize anew
            self._fallback.free()
            U = sp.csr_matrix((np.asarray(upper_data, float), self._upper.indices, self._upper.indptr),
                              shape=self._upper.shape)
            self._fallback = Factorized(U + sp.triu(U, 1).T)
            return
        self._data = np.ascontiguousarray(upper_data, self.dtype)
        self._numeric()

    @property
    def negative_eigenvalues(self) -> int | None:
        """Number of negative eigenvalues of the last factorized matrix (its inertia,
        from PARDISO's Bunch-Kaufman factorization), or None when unknown (SuperLU)."""
        if self._fallback is not None or self.mtype != -2:
            return None
        return self._negative

    @property
    def positive_definite(self) -> bool | None:
        """Whether the last factorized matrix is positive definite: from the failed or
        completed Cholesky factorization (``definite``) or from the inertia; None
        when unknown (SuperLU)."""
        if self._fallback is not None:
            return None
        return self._definite if self.mtype == 2 else self._negative == 0

    @property
    def memory_bytes(self) -> float:
        """The memory one numeric factor of this pattern holds (PARDISO's own
        figure for the factor, iparm[16]; on the demo's tangent 0.154 GB, where
        each new factor sharing the analysis added 0.14-0.23 GB of resident
        memory). The fallback's: its L and U entries."""
        if self._fallback is not None:
            lu = getattr(self._fallback, "_lu", None)
            return 0.0 if lu is None else float(12 * (lu.L.nnz + lu.U.nnz))
        if self._handle is None:
            return 0.0
        return 1024.0 * float(self._handle.s.iparm[16])

    def solve(self, b: np.ndarray) -> np.ndarray:
        if self._fallback is not None:
            return self._fallback.solve(b)
        if not self._definite:
            raise ElastoidError("no factor to solve with: the matrix is not positive definite")
        return self._call(33, np.ascontiguousarray(b, self.dtype)).astype(np.float64)

    @property
    def alive(self) -> bool:
        """Whether it can still solve (not freed)."""
        if self._fallback is not None:
            return self._fallback.alive
        return getattr(self, "_handle", None) is not None

    def free(self) -> None:
        if self._fallback is not None:
            self._fallback.free()
        elif getattr(self, "_handle", None) is not None:
            h = self._handle
            h.users -= 1
            if h.users == 0:  # the last user: the analysis and every factor
                self._call(-1, np.zeros(self.n, self.dtype))
            else:  # this factor only; its number is free for another
                self._call(0, np.zeros(self.n, self.dtype))
                h.free_slots.append(self.mnum)
            self._handle = None

    def __del__(self):  # MKL's memory outlives the Python object unless released
        try:
            self.free()
        except Exception:  # interpreter shutdown: modules may be gone
            pass


def preconditioner(A: sp.spmatrix) -> SymmetricFactor:
    """A factor of the SPD matrix ``A`` to precondition with (a reduced model's
    enrichment): Cholesky in single precision, which on the demo's stiffness
    (52,173 unknowns) took 1.9-2.2 s against 3.8-3.9 s for :class:`Factorized`
    (double precision), with half the memory. Its solutions differ from the
    double-precision ones by about 2e-4 (relative); an enrichment needs only a
    direction, and the reduced model's residual is computed from the matrices
    themselves. Without MKL: :class:`Factorized`, through SymmetricFactor's fallback."""
    U = sp.triu(sp.csr_matrix(A), format="csr")
    U.sort_indices()
    f = SymmetricFactor(U, single=True, definite=True)
    if f.positive_definite is False:
        f.free()
        raise ElastoidError(f"the stiffness matrix ({A.shape[0]:,} unknowns) is not positive definite: "
                            "check the moduli and the boundary conditions")
    return f


def spsolve(A: sp.spmatrix, b: np.ndarray) -> np.ndarray:
    f = Factorized(A)
    try:
        return f.solve(b)
    finally:
        f.free()
