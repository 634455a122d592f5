"""Identification: the paper's cost (-NMI of warped source vs target frames),
the joint cost with the force log, multi-start Nelder-Mead in log-moduli, and an
identifiability report.

Under displacement control the displacement field depends only on the ratios
of the moduli (scaling every modulus scales the stresses, not the strains), so
images alone cannot fix the overall level: the force can. The report makes
this explicit.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.optimize import minimize

from app.core.errors import Cancelled, ElastoidError
from app.core.fem import check_poisson
from app.core.forward import Boundary, FEModel, ReducedModel, build_model, region_terms, training_set
from app.core.images import default_roi, pixel_to_world
from app.core.mesh import MeshSettings, TetMesh, specimen_mesh
from app.core.similarity import NMI, SmoothNMI
from app.core.warp import TPS, FastWarp, WarpGrid, shared_warp
from app.core.solver import single_threaded_blas

PAPER_STARTS_KPA = (10.0, 20.0, 30.0, 40.0, 50.0, 60.0)
RESTARTS = 3  # Nelder-Mead restarts per start (each from where the last stopped)
RESTART_STEP = 0.05  # their simplex size, in log-modulus (5%)
BOUNDS_KPA = (0.1, 1e4)
CONTROL_SPACING_MM = 2.0
# the NMI estimator of the cost: "smooth" (linear partial-volume binning of the
# warped source on the source's range: continuous, no bin-edge steps for the
# simplex to stall on) or "hard" (the paper's, equal to skimage's)
SIMILARITIES = ("smooth", "hard")
DISPLACEMENT_NOISE_PX = 0.25  # stated noise model of the image term (speckle-tracking precision)
# the data-based standard errors: the ROI is cut into blocks of about this size,
# whose speckle is taken as independent (several times the speckle size), dealt
# into JACKKNIFE_GROUPS groups; the cost's derivatives by central differences of
# this step in log-modulus
JACKKNIFE_BLOCK_MM = 3.0
JACKKNIFE_GROUPS = 16
SANDWICH_STEP = 0.03


@dataclass(frozen=True)
class EvalReport:
    """One cost evaluation, as reported to progress callbacks."""

    start: int
    evaluation: int
    parameters: dict
    cost: dict


@dataclass
class _FramePair:
    source: int
    target: int
    d_source_mm: float
    d_target_mm: float
    warp: FastWarp
    nmi: NMI
    mask: np.ndarray  # ROI pixels whose source pre-image lies inside the source frame
    source_image: np.ndarray
    target_roi: np.ndarray


def force_noise_N(force_N: np.ndarray) -> float:
    """Robust noise estimate of a force log: MAD of second differences (trend-free)."""
    d2 = np.diff(np.asarray(force_N, float), 2)
    if len(d2) < 3:
        return float("nan")
    return float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / math.sqrt(6.0))


# the most frames compared by default, the source included. Cost and memory grow
# with every frame: at paper size 31 frames (one every half millimetre) took a
# diagnosis 3.3 minutes and 6.1 GB, and a scanner recording a slow indentation at
# video rate gives hundreds. Frames that close add little: the tracking between
# them is already at its noise (bench/paper_effects.py, case slip-31).
MAX_DEFAULT_FRAMES = 31


def _deeper(exp, source: int) -> list[int]:
    """Every frame with more probe travel than frame ``source``, in the order recorded."""
    d0 = exp.frames[source].displacement_mm
    return [i for i, f in enumerate(exp.frames) if i != source and f.displacement_mm > d0 + 1e-9]


def later_frames(exp, source: int = 0, keep=(), limit: int = MAX_DEFAULT_FRAMES) -> tuple[int, ...]:
    """The frames compared with ``source`` by default: every other frame with more
    probe travel, in the order recorded. More than ``limit - 1`` of them are thinned
    to that many spread evenly along the probe's path (its travel summed over the
    recording, loading and unloading alike; a hold adds nothing, so its frames,
    which see the same field, do not crowd out the others), keeping the deepest
    and those of ``keep`` that are among them."""
    later = _deeper(exp, source)
    if len(later) <= limit - 1:
        return tuple(later)
    d = np.array([exp.frames[i].displacement_mm for i in later])
    path = np.concatenate([[0.0], np.cumsum(np.abs(np.diff(d)))])
    if path[-1] <= 1e-9:  # every frame at one travel: spread over the recording
        path = np.arange(len(later), dtype=float)
    picked = {later[int(np.argmin(np.abs(path - t)))] for t in np.linspace(0.0, path[-1], limit - 1)}
    musts = [later[int(np.argmax(d))], *(i for i in keep if i in later)]
    for must in musts:  # each takes the place of the nearest frame picked
        if must not in picked:
            if len(picked) >= limit - 1:
                picked.remove(min((i for i in picked if i not in musts), key=lambda i: abs(i - must)))
            picked.add(must)
    return tuple(sorted(picked))


def thinned_note(exp, chosen) -> str:
    """What a progress line says when the default frames ``chosen`` were thinned
    (:func:`later_frames`); "" when every deeper frame is compared."""
    n = len(_deeper(exp, chosen[0]))
    if n <= len(chosen) - 1:
        return ""
    return (f"comparing {len(chosen) - 1} of the {n} frames deeper than frame {chosen[0]}, spread along the "
            "probe's travel (frames that close add little, and each costs time and memory)")


def chosen_frames(exp, frames, say: Callable[[str], None]) -> tuple[int, ...]:
    """:func:`frame_indices` for a model being built, saying through ``say`` when the
    default frames leave some out (:func:`thinned_note`)."""
    out = frame_indices(exp, frames)
    note = thinned_note(exp, out) if frames is None else ""
    if note:
        say(note)
    return out


def frame_indices(exp, frames=None, what: str = "frames") -> tuple[int, ...]:
    """The frames a cost compares, the first the source (pre-deformation) frame:
    by default frame 0 and every later frame with more probe travel
    (:func:`later_frames`: at most MAX_DEFAULT_FRAMES in all). Given indices may
    count from the end (-1: the last frame); each must exist and appear once.
    ElastoidError (naming ``what``) otherwise."""
    n = len(exp.frames)
    if frames is None:
        out = (0,) + later_frames(exp)
    else:
        out = []
        for i in frames:
            if isinstance(i, bool) or int(i) != i or not -n <= int(i) < n:
                raise ElastoidError(f"{what}: there is no frame {i!r}: the experiment has {n} frames, 0 to {n - 1}")
            out.append(int(i) % n)
        twice = sorted({i for i in out if out.count(i) > 1})
        if twice:
            raise ElastoidError(f"{what}: frame {twice[0]} is given twice (the first frame is the source, and each "
                                "other frame is compared with it)")
        out = tuple(out)
    if len(out) < 2:
        raise ElastoidError("identification needs a source frame and at least one deformed frame")
    return out


# the smallest ROI compared, each way: a smaller one holds too few speckles for the
# similarity and a single tracking block (about 3 mm, 16 px at 0.2 mm): a 2 x 2 px
# ROI on the demo gave E_A 27 kPa for 63, reported "ok" at +/-0.3%
MIN_ROI_PX = 32


def check_roi(exp, roi_px=None, what: str = "ROI", shape=None) -> tuple[int, int, int, int]:
    """The region of interest a cost compares: ``roi_px`` (col0, row0, col1, row1,
    ends exclusive) or the experiment's default, checked against frame 0's size
    before anything is meshed. ElastoidError naming ``what`` when it is not inside
    the images or smaller than MIN_ROI_PX each way. ``shape``: the frames' (rows,
    columns) when known (else frame 0 is read for it)."""
    rows, cols = (shape if shape is not None else exp.image(0).shape)[:2]
    roi = tuple(roi_px) if roi_px is not None else default_roi(exp, (rows, cols))
    if len(roi) != 4 or any(isinstance(v, bool) or int(v) != v for v in roi):
        raise ElastoidError(f"{what}: expected four whole numbers col0,row0,col1,row1, got {list(roi)}")
    c0, r0, c1, r1 = (int(v) for v in roi)
    if c1 <= c0 or r1 <= r0:
        raise ElastoidError(f"{what}: {list(roi)} is empty: col1 must exceed col0 and row1 row0 (the ends are "
                            "exclusive)")
    if c0 < 0 or r0 < 0 or c1 > cols or r1 > rows:
        raise ElastoidError(f"{what}: {list(roi)} reaches outside the {cols} x {rows} px images (columns 0 to "
                            f"{cols}, rows 0 to {rows}, ends exclusive)")
    if c1 - c0 < MIN_ROI_PX or r1 - r0 < MIN_ROI_PX:
        raise ElastoidError(f"{what}: {list(roi)} is {c1 - c0} x {r1 - r0} px; the comparison needs at least "
                            f"{MIN_ROI_PX} x {MIN_ROI_PX} px")
    return c0, r0, c1, r1


class Problem:
    """Everything an evaluation needs, built once: mesh, FE operator, reduced
    model, warps and NMI objects for each (source, target) frame pair."""

    def __init__(self, exp, mesh: TetMesh, fe: FEModel, rm: ReducedModel, *, nu: float, cost: str,
                 frames: tuple[int, ...], roi_px, force_weight: float, bins: int, similarity: str = "smooth"):
        if cost not in ("nmi", "joint"):
            raise ElastoidError(f"cost must be 'nmi' or 'joint', got {cost!r}")
        if similarity not in SIMILARITIES:
            raise ElastoidError(f"similarity must be one of {', '.join(SIMILARITIES)}, got {similarity!r}")
        self.similarity = similarity
        self.exp, self.mesh, self.fe, self.rm = exp, mesh, fe, rm
        self.nu, self.cost_kind, self.force_weight, self.bins = nu, cost, force_weight, bins
        self.region_names = mesh.region_names
        self.parameter_names = tuple(f"E_{n}_kPa" for n in self.region_names)
        self.frames = frames
        log = exp.force_log
        self.log_d = np.clip(log.displacement_mm, 0.0, None)
        self.log_F = log.force_N
        self.force_scale_N = max(float(np.abs(self.log_F).max()), 1e-9)
        self.force_sigma_N = force_noise_N(self.log_F)
        img0 = exp.image(frames[0])
        self.image_shape = img0.shape
        self.roi = check_roi(exp, roi_px, shape=img0.shape)
        c0, r0, c1, r1 = self.roi
        self._setup_control_points()
        grid = WarpGrid(c0, r0, c1, r1)
        self.pairs: list[_FramePair] = []
        ref = np.ones(len(self.region_names))
        warp = shared_warp(self.tps, img0.shape, grid)  # the same for every pair (and model)
        for t in frames[1:]:
            tgt = exp.image(t)
            pair = _FramePair(frames[0], t, exp.frames[frames[0]].displacement_mm, exp.frames[t].displacement_mm,
                              warp, None, None, img0, tgt[r0:r1, c0:c1])
            rows, cols = warp.sample_positions(coarse=self._coarse_field(pair, self.rm.coords(ref)))
            H, W = img0.shape
            pair.mask = (rows >= 2) & (rows <= H - 3) & (cols >= 2) & (cols <= W - 3)
            if pair.mask.mean() < 0.25:
                raise ElastoidError(
                    f"frame {t}: only {100 * pair.mask.mean():.0f}% of the ROI was imaged in the source frame; "
                    "choose a shallower ROI")
            if similarity == "smooth":
                pair.nmi = SmoothNMI(pair.target_roi[pair.mask], bins, (float(img0.min()), float(img0.max())))
            else:
                pair.nmi = NMI(pair.target_roi[pair.mask], bins=bins)
            self.pairs.append(pair)
        self.n_evaluations = 0

    # --- construction -----------------------------------------------------
    @classmethod
    def from_experiment(cls, exp, *, mesh: TetMesh | None = None, mesh_settings: MeshSettings | None = None,
                        roi_px=None, frames=None, cost: str = "joint", nu: float = 0.49,
                        boundary: Boundary = Boundary(), force_weight: float = 1.0, bins: int = 32,
                        similarity: str = "smooth", progress: Callable[[str], None] | None = None,
                        cancel: threading.Event | None = None) -> "Problem":
        """Mesh (cached), assemble, train the reduced model and prepare the frames.

        ``frames``: indices, the first is the source (pre-deformation) frame; by
        default frame 0 against every later frame with larger probe travel.
        """
        say = progress or (lambda s: None)
        frames = chosen_frames(exp, frames, say)
        nu = check_poisson(nu)
        check_roi(exp, roi_px)
        if mesh is None:
            mesh = specimen_mesh(exp, mesh_settings, progress=say, cancel=cancel)
        say("assembling the finite-element model")
        fe = build_model(mesh, boundary)
        if cancel is not None and cancel.is_set():
            raise Cancelled("cancelled")
        say("training the reduced model")
        with single_threaded_blas():
            rm = ReducedModel(fe, region_terms(len(mesh.region_names), nu))
            rm.train(training_set(len(mesh.region_names)))
        say(f"reduced model: {rm.V.shape[1]} basis vectors")
        return cls(exp, mesh, fe, rm, nu=nu, cost=cost, frames=frames, roi_px=roi_px,
                   force_weight=force_weight, bins=bins, similarity=similarity)

    def _setup_control_points(self):
        """Grid of control points on the source image plane (2 mm apart, with a margin)."""
        exp = self.exp
        H, W = self.image_shape
        sc, sr = exp.imaging.pixel_spacing_mm
        step_c, step_r = CONTROL_SPACING_MM / sc, CONTROL_SPACING_MM / sr
        cols = np.arange(-2 * step_c, W + 2 * step_c, step_c)
        rows = np.arange(0.0, H + 2 * step_r, step_r)
        C, R = np.meshgrid(cols, rows)
        self.ctrl_px = np.column_stack([C.ravel(), R.ravel()])
        d0 = exp.frames[self.frames[0]].displacement_mm
        pts = pixel_to_world(self.ctrl_px[:, 0], self.ctrl_px[:, 1], exp, d0)
        # keep the points inside the specimen (clamped to it): the field is not defined outside
        size = np.asarray(exp.specimen.size_mm)
        pts = np.clip(pts, 0.0, size)
        self.ctrl_world = pts
        self.tps = TPS(self.ctrl_px)
        self._pointop = self.rm.point_operator(pts)
        lat = np.asarray(exp.probe.lateral_axis, float)
        self._lat, self._sc, self._sr = lat, sc, sr

    # --- model pieces -----------------------------------------------------
    def theta(self, params: dict) -> np.ndarray:
        return np.array([params[n] for n in self.parameter_names], float)

    def control_displacement_px(self, a: np.ndarray, pair: _FramePair) -> np.ndarray:
        """delta (n_ctrl, 2) px (col, row) from the source frame to the target frame."""
        u = self._pointop.values(a)  # per mm of travel
        dd = pair.d_target_mm - pair.d_source_mm
        col = dd * (u @ self._lat) / self._sc
        row = dd * (-1.0 - u[:, 2]) / self._sr
        return np.column_stack([col, row])

    def _coarse_field(self, pair: _FramePair, a: np.ndarray) -> np.ndarray:
        """Forward displacement (px) on the warp's coarse source grid. The chain
        reduced coordinates -> control points -> TPS on the grid is linear, so it is
        precomposed into one small matrix, shared by the pairs as their warp is (rebuilt
        if the basis grows); a pair scales it by its travel."""
        key = (id(pair.warp), self.rm.k)  # the pairs share their warp, and so this
        cache = self.__dict__.setdefault("_G", {})
        if key not in cache:
            self._pointop.values(np.zeros(self.rm.k))  # make sure B matches the basis
            B = self._pointop.B.reshape(-1, 3, self.rm.k)  # (n_ctrl, xyz, k) per mm
            l = self._pointop.lift_part.reshape(-1, 3)
            Bc = np.einsum("nck,c->nk", B, self._lat) / self._sc
            Br = -B[:, 2, :] / self._sr
            lc = (l @ self._lat) / self._sc
            lr = (-1.0 - l[:, 2]) / self._sr
            M = pair.warp.M
            cache[key] = (M @ Bc, M @ Br, M @ lc, M @ lr)
        Gc, Gr, gc, gr = cache[key]
        dd = pair.d_target_mm - pair.d_source_mm
        shape = (len(pair.warp.src_rows), len(pair.warp.src_cols))
        return np.stack([(dd * (Gc @ a + gc)).reshape(shape), (dd * (Gr @ a + gr)).reshape(shape)], axis=-1)

    def model_force_N(self, params: dict, a=None) -> np.ndarray:
        theta = self.theta(params)
        g = self.rm.force_N_per_mm(theta, a)
        return g * self.log_d

    def warped_source(self, params: dict, target: int | None = None):
        """(warped source ROI, target ROI, roi, mask) for a target frame index."""
        a = self.rm.coords(self.theta(params))
        pair = self.pairs[0] if target is None else next(p for p in self.pairs if p.target == target)
        w = pair.warp(pair.source_image, coarse=self._coarse_field(pair, a))
        return w, pair.target_roi, self.roi, pair.mask

    def complete(self, params: dict) -> dict:
        """Parameters with defaults filled in (the baseline has none; effects add theirs)."""
        return params

    def evaluate(self, params: dict) -> dict:
        """Cost parts: total, nmi (mean over frame pairs, in [1, 2]), force_rms_N."""
        params = self.complete(params)
        with single_threaded_blas():
            theta = self.theta(params)
            a = self.rm.coords(theta)
            vals = []
            for pair in self.pairs:
                w = pair.warp(pair.source_image, coarse=self._coarse_field(pair, a))
                vals.append(pair.nmi(w[pair.mask]))
            nmi = float(np.mean(vals))
            resid = self.model_force_N(params, a) - self.log_F
            frms = float(np.sqrt(np.mean(resid**2)))
        self.n_evaluations += 1
        total = -nmi
        if self.cost_kind == "joint":
            total += self.force_weight * (frms / self.force_scale_N) ** 2
        return {"total": total, "nmi": nmi, "force_rms_N": frms}

    def deformed_points(self, params: dict, displacement_mm: float) -> np.ndarray:
        """Mesh vertices moved by the model at a probe travel (mm)."""
        a = self.rm.coords(self.theta(self.complete(params)))
        u = self.rm.full_field(a).reshape(-1, 3)[: self.mesh.n_nodes]
        return self.mesh.points_mm + displacement_mm * u

    # --- identifiability ----------------------------------------------------
    def identifiability(self, params: dict) -> "Identifiability":
        theta = self.theta(params)
        names = self.parameter_names
        h = 1e-4
        base_u, base_F = self._observables(theta)
        Su, SF = [], []
        for r in range(len(theta)):
            tp = theta.copy()
            tp[r] *= math.exp(h)
            u, F = self._observables(tp)
            Su.append((u - base_u) / h)
            SF.append((F - base_F) / h)
        Su, SF = np.column_stack(Su), np.column_stack(SF)
        sigma_F = self.force_sigma_N if np.isfinite(self.force_sigma_N) and self.force_sigma_N > 0 else 0.01
        fisher = Su.T @ Su / DISPLACEMENT_NOISE_PX**2
        if self.cost_kind == "joint":
            fisher = fisher + SF.T @ SF / sigma_F**2
        ident = Identifiability.from_fisher(names, fisher, Su, SF, sigma_F, self.cost_kind)
        try:
            cov, unseen, falling = self.data_covariance(params, unseen=[np.asarray(v) for v in ident.null_directions])
        except (np.linalg.LinAlgError, ValueError):  # too few blocks, a degenerate Hessian
            return ident
        return ident.with_data_covariance(cov, unseen, falling)

    # --- standard errors from the data --------------------------------------------
    def _jackknife_groups(self, pair) -> tuple:
        """(smooth NMI on all the pair's masked ROI pixels, [(kept pixel indices, smooth
        NMI on them) for each group of blocks left out]), built once per pair."""
        cached = getattr(pair, "_jackknife", None)
        if cached is not None:
            return cached
        rows, cols = np.nonzero(pair.mask)
        b_r = max(1, int(round(JACKKNIFE_BLOCK_MM / self._sr)))
        b_c = max(1, int(round(JACKKNIFE_BLOCK_MM / self._sc)))
        block = (rows // b_r) * (cols.max() // b_c + 1) + cols // b_c
        ids, block = np.unique(block, return_inverse=True)
        if len(ids) < 2 * JACKKNIFE_GROUPS:
            raise ValueError(f"only {len(ids)} blocks of {JACKKNIFE_BLOCK_MM:g} mm in the ROI")
        group = (np.random.default_rng(0).permutation(len(ids)) % JACKKNIFE_GROUPS)[block]
        target = pair.target_roi[pair.mask]
        span = (float(pair.source_image.min()), float(pair.source_image.max()))
        # the cost's own estimator when it is the smooth one (the derivatives need it smooth)
        full = pair.nmi if isinstance(pair.nmi, SmoothNMI) else SmoothNMI(target, self.bins, span)
        # int32 indices: 16 of them per pair, each over about 94% of the ROI's pixels
        parts = [(keep, SmoothNMI(target[keep], self.bins, span))
                 for keep in (np.flatnonzero(group != g).astype(np.int32) for g in range(JACKKNIFE_GROUPS))]
        pair._jackknife = (full, parts)
        return pair._jackknife

    def _cost_parts(self, x: np.ndarray):
        """At log-moduli ``x``, with the smooth NMI estimator: (image cost of all
        pixels, image cost with each group of blocks left out (G,), force cost, the
        model's force over the log)."""
        return self.cost_parts(self.complete(dict(zip(self.parameter_names, np.exp(x)))))

    def cost_parts(self, params: dict):
        """:meth:`_cost_parts` at parameters ``params`` (every one, by name)."""
        a = self.rm.coords(self.theta(params))
        full, parts = [], []
        for pair in self.pairs:
            full_nmi, groups = self._jackknife_groups(pair)
            w = pair.warp(pair.source_image, coarse=self._coarse_field(pair, a))[pair.mask]
            full.append(full_nmi(w))
            parts.append([nmi(w[keep]) for keep, nmi in groups])
        F = self.model_force_N(params, a)
        force = 0.0
        if self.cost_kind == "joint":
            frms = float(np.sqrt(np.mean((F - self.log_F) ** 2)))
            force = self.force_weight * (frms / self.force_scale_N) ** 2
        return -float(np.mean(full)), -np.mean(np.array(parts), axis=0), force, F

    def data_covariance(self, params: dict, unseen=()) -> tuple[np.ndarray, list]:
        """Covariance of the log-moduli at an optimum from the data (the sandwich
        H^-1 V H^-1 of an M-estimator): H, the cost's Hessian, by central
        differences; V, the variance of the cost's gradient: for the image term by
        the delete-a-group jackknife over groups of ROI blocks (speckle in separate
        blocks independent; nothing else assumed about the image noise), for the
        force term from independent noise of the log's estimated sigma per sample.
        ``unseen``: directions of the log-moduli the cost does not depend on (the
        overall level with the NMI-only cost: the sensitivities' null space); the
        Hessian is inverted on their complement (finite differences leave a few
        percent of curvature along them). Returns (covariance within the directions
        the cost sees, the unseen directions plus any the Hessian shows flat or
        falling, the falling ones alone: directions along which the cost still
        decreases, so that ``params`` is not a minimum of it)."""
        x0 = np.log(self.theta(self.complete(params)))
        n, h = len(x0), SANDWICH_STEP
        E = np.eye(n) * h

        def total(x):
            image, _, force, _ = self._cost_parts(x)
            return image + force

        with single_threaded_blas():
            f0 = total(x0)
            H = np.zeros((n, n))
            plus_minus = [(self._cost_parts(x0 + E[i]), self._cost_parts(x0 - E[i])) for i in range(n)]
            for i, ((ip, jp, fp, _), (im, jm, fm, _)) in enumerate(plus_minus):
                H[i, i] = (ip + fp - 2 * f0 + im + fm) / h**2
            for i in range(n):
                for j in range(i + 1, n):
                    fpp = total(x0 + E[i] + E[j])
                    fmm = total(x0 - E[i] - E[j])
                    fpm = total(x0 + E[i] - E[j])
                    fmp = total(x0 - E[i] + E[j])
                    H[i, j] = H[j, i] = (fpp - fpm - fmp + fmm) / (4 * h * h)
        # (groups, n): the image term's gradient with each group of blocks left out
        G = np.column_stack([(p[1] - m[1]) / (2 * h) for p, m in plus_minus])
        k = len(G)
        D = G - G.mean(axis=0)
        V = (k - 1) / k * D.T @ D
        if self.cost_kind == "joint" and np.isfinite(self.force_sigma_N) and self.force_sigma_N > 0:
            S = np.column_stack([(p[3] - m[3]) / (2 * h) for p, m in plus_minus])  # dF/dlog(E)
            c = 2 * self.force_weight / (len(self.log_F) * self.force_scale_N**2)
            V = V + c * c * self.force_sigma_N**2 * S.T @ S
        # the directions the cost sees: the complement of the unseen ones
        N = np.array([np.asarray(u, float) / np.linalg.norm(u) for u in unseen]).reshape(-1, n)
        U, sv, _ = np.linalg.svd(np.eye(n) - N.T @ N)
        B = U[:, sv > 0.5]
        w, Q = np.linalg.eigh(B.T @ (0.5 * (H + H.T)) @ B)
        if len(w) == 0 or w.max() <= 0:
            raise ValueError("the cost has no curvature at this point")
        good = w > 1e-6 * w.max()
        Bq = B @ Q
        Hinv = (Bq[:, good] / w[good]) @ Bq[:, good].T
        falling = [Bq[:, i] for i in np.flatnonzero(w < -1e-6 * w.max())]
        return Hinv @ V @ Hinv, list(N) + [Bq[:, i] for i in np.flatnonzero(~good)], falling

    def _observables(self, theta):
        a = self.rm.coords(theta)
        u = np.concatenate([self.control_displacement_px(a, p).ravel() for p in self.pairs])
        F = self.rm.force_N_per_mm(theta, a) * self.log_d
        return u, F


def percent_text(rel: float) -> str:
    """A relative error as a percentage: one decimal, or two significant digits
    under 0.1% (the demo's E_B, 0.024% from the noise model, printed as "0.0%" read as no
    error at all)."""
    v = 100.0 * float(rel)
    return f"{v:.2g}%" if 0 < v < 0.1 else f"{v:.1f}%"


def parameter_text(name: str, value: float) -> str:
    """A parameter and its value in words: a modulus as "E_B 17.80 kPa", any other
    parameter as "g1 0.3"."""
    return f"{name[:-4]} {value:.2f} kPa" if name.endswith("_kPa") else f"{name} {value:.3g}"


@dataclass
class Identifiability:
    """Sensitivities at the optimum, standard errors from a stated noise model,
    parameter correlations and a flag per parameter."""

    names: tuple
    standard_error_rel: dict
    correlation: np.ndarray
    flags: dict
    image_sensitivity_px: dict  # max displacement change (px) for a 10% change of the parameter
    force_sensitivity_N: dict  # max force change (N) for a 10% change
    null_directions: list
    noise_model: str
    # from the data (Problem.data_covariance): relative standard errors, and of each
    # modulus ratio to the first region's; None when not computed
    standard_error_rel_data: dict | None = None
    ratio_standard_error_rel_data: dict | None = None
    # directions of the log-moduli along which the cost still falls at the reported
    # point (a negative curvature of its Hessian): not a minimum there
    falling_directions: list = field(default_factory=list)

    @classmethod
    def from_fisher(cls, names, fisher, Su, SF, sigma_F, cost_kind):
        w, V = np.linalg.eigh(fisher)
        tol = max(w.max(), 1e-300) * 1e-9
        null = [V[:, i] for i in range(len(w)) if w[i] <= tol]
        cov = np.linalg.pinv(fisher, rcond=1e-9, hermitian=True)
        se = np.sqrt(np.clip(np.diag(cov), 0, None))
        d = np.where(se > 0, se, 1.0)
        corr = cov / np.outer(d, d)
        flags = {}
        for i, n in enumerate(names):
            in_null = any(abs(v[i]) > 1e-3 for v in null)
            if in_null:
                flags[n] = "unconstrained: the data fix only ratios involving it"
            elif se[i] > 0.25:
                flags[n] = f"weakly constrained (+/-{100 * se[i]:.0f}%)"
            else:
                flags[n] = "ok"
        ln = math.log(1.1)
        img = {n: float(np.abs(Su[:, i]).max() * ln) for i, n in enumerate(names)}
        frc = {n: float(np.abs(SF[:, i]).max() * ln) for i, n in enumerate(names)}
        noise = (f"image term: independent {DISPLACEMENT_NOISE_PX} px error on each control-point displacement "
                 f"({CONTROL_SPACING_MM:g} mm grid)")
        if cost_kind == "joint":
            noise += f"; force term: independent {sigma_F:.3g} N noise per sample (estimated from the log)"
        return cls(tuple(names), {n: (float("inf") if flags[n].startswith("unconstrained") else float(se[i]))
                                  for i, n in enumerate(names)},
                   corr, flags, img, frc, [v.tolist() for v in null], noise)

    def with_data_covariance(self, cov: np.ndarray, unseen=(), falling=()) -> "Identifiability":
        """This report with standard errors from the data (``cov``: covariance of the
        log-moduli within the directions the cost sees; ``unseen``: the others, along
        which the variance is infinite; ``falling``: those of them along which the
        cost still decreases): they become the flags' basis, and the ratios to the
        first region's modulus get theirs. A parameter along a falling direction is
        flagged as such: no standard error means something there, because the
        point is not a minimum of the cost (a model the data do not follow, whose
        fit stopped on a compromise, e.g. large deformation fitted to a linear
        specimen)."""
        from dataclasses import replace

        def touches(direction, among):
            return any(abs(float(np.dot(direction, u))) > 1e-3 for u in among)

        def se_of(direction):
            if touches(direction, unseen):
                return float("inf")
            return float(np.sqrt(max(float(direction @ cov @ direction), 0.0)))

        n = len(self.names)
        eye = np.eye(n)
        data = {name: se_of(eye[i]) for i, name in enumerate(self.names)}
        ratios = {f"{self.names[i]}/{self.names[0]}": se_of(eye[i] - eye[0]) for i in range(1, n)}
        flags = dict(self.flags)
        for n, v in data.items():
            if flags[n].startswith("unconstrained"):
                continue
            if touches(np.eye(len(self.names))[self.names.index(n)], falling):
                flags[n] = "not at a minimum of the cost: it still falls along a direction involving this modulus"
            elif not np.isfinite(v) or v > 0.25:
                flags[n] = f"weakly constrained by the data (+/-{100 * v:.0f}%)" if np.isfinite(v) else \
                    "not constrained by the data"
            elif v > 0.05:
                flags[n] = f"ok, within +/-{100 * v:.0f}% (one standard error)"
            else:
                flags[n] = "ok"
        return replace(self, standard_error_rel_data=data, ratio_standard_error_rel_data=ratios, flags=flags,
                       falling_directions=[np.asarray(u, float).tolist() for u in falling])

    def lines(self) -> list[str]:
        out = [f"noise model: {self.noise_model}"]
        if self.standard_error_rel_data is not None:
            out.append(f"standard errors from the data: the speckle of separate {JACKKNIFE_BLOCK_MM:g} mm blocks of "
                       f"the ROI taken as independent (jackknife over {JACKKNIFE_GROUPS} groups of blocks)"
                       + ("; the force's noise as above" if "force term" in self.noise_model else ""))
        for n in self.names:
            se = self.standard_error_rel[n]
            se_s = "undetermined" if not np.isfinite(se) else f"+/-{percent_text(se)}"
            if self.standard_error_rel_data is not None:
                sd = self.standard_error_rel_data[n]
                se_s = ("undetermined by the data" if not np.isfinite(sd) else f"+/-{percent_text(sd)} from the data") \
                    + f" ({se_s} from the noise model)"
            out.append(f"{n}: {se_s}; 10% change moves the image by {self.image_sensitivity_px[n]:.2f} px "
                       f"and the force by {self.force_sensitivity_N[n]:.3f} N; {self.flags[n]}")
        for r, v in (self.ratio_standard_error_rel_data or {}).items():
            out.append(f"ratio {r}: " + (f"+/-{percent_text(v)} from the data" if np.isfinite(v) else "undetermined"))
        for v in self.falling_directions:
            out.append("the cost still falls when the log-moduli move along (" + ", ".join(
                f"{n} {x:+.2f}" for n, x in zip(self.names, v) if abs(x) > 1e-3)
                + "), either way: this is not a minimum, so the standard errors involving it are undetermined; "
                "the fit settled on a compromise, which happens when the model is not the one the data follow")
        for v in self.null_directions:
            if np.allclose(np.abs(v), abs(v[0]), atol=1e-3):
                out.append("the images cannot tell the overall stiffness level (all moduli scaled together): "
                           "use the joint cost with the force")
            else:
                out.append("unconstrained direction (log-moduli): " + ", ".join(f"{x:+.2f}" for x in v))
        if len(self.names) > 1:
            out.append("correlations: " + "; ".join(
                f"{self.names[i]}~{self.names[j]} {self.correlation[i, j]:+.2f}"
                for i in range(len(self.names)) for j in range(i + 1, len(self.names))))
        return out

    def to_dict(self) -> dict:
        def finite(d):
            return None if d is None else {k: (None if not np.isfinite(v) else v) for k, v in d.items()}

        return {"standard_error_rel": finite(self.standard_error_rel),
                "standard_error_rel_data": finite(self.standard_error_rel_data),
                "ratio_standard_error_rel_data": finite(self.ratio_standard_error_rel_data),
                "flags": self.flags, "image_sensitivity_px": self.image_sensitivity_px,
                "force_sensitivity_N": self.force_sensitivity_N, "correlation": self.correlation.tolist(),
                "falling_directions": self.falling_directions, "noise_model": self.noise_model}


@dataclass
class Result:
    parameters: dict
    cost: dict
    evaluations: int
    seconds: float
    history: list = field(default_factory=list)
    starts: list = field(default_factory=list)
    identifiability: Identifiability | None = None
    effects: tuple = ()
    experiment: str = ""

    def ratios(self) -> dict:
        names = list(self.parameters)
        base = self.parameters[names[0]]
        return {f"{n}/{names[0]}": self.parameters[n] / base for n in names[1:]}

    def to_json_dict(self) -> dict:
        return {"experiment": self.experiment, "effects": list(self.effects), "parameters": self.parameters,
                "cost": self.cost, "evaluations": self.evaluations, "seconds": round(self.seconds, 3),
                "starts": self.starts,
                "identifiability": self.identifiability.to_dict() if self.identifiability else None}


def nelder_mead(f, x0, step: float, *, xatol: float, fatol: float, max_evaluations: int, count=None):
    """Nelder-Mead from ``x0`` with an initial simplex of ``step`` along each axis,
    restarted from where it stopped with a fresh ``RESTART_STEP`` simplex until a
    restart no longer improves (at most ``RESTARTS``).

    A simplex can collapse in a long valley (the joint cost has one: the force
    fixes one combination of the moduli, the images another) and stop short of
    the minimum; restarting is the standard remedy. ``count`` (a one-item list
    ``f`` increments) bounds the evaluations of all rounds together."""
    x0 = np.asarray(x0, float)
    n = len(x0)
    count = count if count is not None else [0]
    opts = {"xatol": xatol, "fatol": fatol}

    def simplex(x, h):
        return np.vstack([x] + [x + h * np.eye(n)[i] for i in range(n)])

    start = count[0]
    res = minimize(f, x0, method="Nelder-Mead",
                   options={**opts, "initial_simplex": simplex(x0, step), "maxfev": max_evaluations})
    for _ in range(RESTARTS):
        left = max_evaluations - (count[0] - start)
        if left <= n + 1:
            break
        r2 = minimize(f, res.x, method="Nelder-Mead",
                      options={**opts, "initial_simplex": simplex(res.x, RESTART_STEP), "maxfev": left})
        improved = r2.fun < res.fun - fatol
        if r2.fun < res.fun:
            res = r2
        if not improved:
            break
    return res


def check_starts(starts_kPa, what: str = "starts") -> None:
    """Start moduli: at least one, each a positive finite number of kPa (the
    search runs in log-moduli). ElastoidError naming ``what`` otherwise."""
    starts = list(starts_kPa)
    if not starts:
        raise ElastoidError(f"{what}: give at least one start modulus (kPa)")
    for s in starts:
        try:
            v = float(s)
        except (TypeError, ValueError):
            v = math.nan
        if not (math.isfinite(v) and v > 0):
            raise ElastoidError(f"{what}: start moduli must be positive numbers of kPa, got {s!r}")


def identify(problem: Problem, starts_kPa=PAPER_STARTS_KPA, *, fixed: dict | None = None,
             progress: Callable[[EvalReport], None] | None = None, cancel: threading.Event | None = None,
             max_evaluations: int = 200, xatol: float = 2e-3, fatol: float = 1e-6) -> Result:
    """Multi-start Nelder-Mead in log-moduli. Each start sets every free modulus to
    the start value (the paper's starts: 10, 20, ..., 60 kPa). ``fixed`` holds
    parameters kept at given values. Reports every evaluation to ``progress``.

    With the image-only cost the overall level is not identifiable (the cost is
    exactly invariant to scaling all moduli), so the first free modulus stays at
    the start value and only the ratios are searched."""
    t0 = time.perf_counter()
    check_starts(starts_kPa)
    fixed = dict(fixed or {})
    free = [n for n in problem.parameter_names if n not in fixed]
    if not free:
        raise ElastoidError("every parameter is fixed: nothing to identify")
    ratio_only = problem.cost_kind == "nmi" and len(free) > 1 and not fixed
    lo, hi = np.log(BOUNDS_KPA)
    history: list[EvalReport] = []
    per_start = []
    best = None
    total_evals = 0
    for k, s in enumerate(starts_kPa):
        count = [0]
        anchor = {free[0]: float(s)} if ratio_only else {}
        search = free[1:] if ratio_only else free

        def params_of(x):
            xc = np.clip(x, lo, hi)
            params = dict(fixed)
            params.update(anchor)
            params.update({n: float(math.exp(v)) for n, v in zip(search, xc)})
            return {n: params[n] for n in problem.parameter_names}, xc

        def f(x, k=k):
            if cancel is not None and cancel.is_set():
                raise Cancelled("identification cancelled")
            params, xc = params_of(x)
            cost = problem.evaluate(params)
            count[0] += 1
            rep = EvalReport(k, count[0], params, cost)
            history.append(rep)
            if progress:
                progress(rep)
            return cost["total"] + float(np.sum((x - xc) ** 2))

        x0 = np.full(len(search), math.log(s))
        res = nelder_mead(f, x0, 0.3, xatol=xatol, fatol=fatol, max_evaluations=max_evaluations, count=count)
        params, _ = params_of(res.x)
        cost = problem.evaluate(params)
        total_evals += count[0]
        per_start.append({"start_kPa": s, "parameters": params, "cost": cost, "evaluations": count[0]})
        if best is None or cost["total"] < best[1]["total"]:
            best = (params, cost)
    ident = problem.identifiability(best[0])
    return Result(parameters=best[0], cost=best[1], evaluations=total_evals, seconds=time.perf_counter() - t0,
                  history=history, starts=per_start, identifiability=ident,
                  experiment=str(problem.exp.path or ""))
