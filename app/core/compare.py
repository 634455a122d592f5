"""Model against measurement: where and how the identified model fails.

- the force over the whole log (loading, hold, unloading), measured and modelled;
- per frame, a residual map: where the warped source disagrees with the frame
  (1 - windowed normalized cross-correlation, :func:`app.core.similarity.local_similarity`);
- per frame, the displacement measured on the image plane by speckle tracking,
  the model's at the same points, and their difference (a vector map);
- each region's share of the misfit.

Speckle tracking is model-assisted block matching: the target frame is sampled
at the positions the model says each source pixel moved to (unwarping the
model's deformation, so the blocks compare near-rigidly even at large strain),
and the small remaining shift of each block is the peak of the normalized
cross-correlation (:func:`skimage.feature.match_template`) over a +-4 px
search, refined to sub-pixel by a parabola per axis; the target is then
resampled at the shifted positions and matched again until the remaining shift
vanishes (a parabola alone is biased toward whole pixels, which would pull the
measurement toward the model it started from). The measured
displacement is the model's plus that shift, so it does not depend on the model
to first order. Blocks tile the ROI without overlap, so their errors are
independent; the tracking noise is estimated from the blocks themselves (the
scatter of second differences across neighbouring blocks, which a smooth
misfit does not reach).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import map_coordinates

from app.core.images import pixel_to_world
from app.core.similarity import local_similarity


@dataclass(frozen=True)
class TrackedPair:
    """Displacements of one frame pair at block centres, source-frame pixels.

    ``points_px`` (n, 2) col, row in the source frame; displacements (n, 2) px
    (col, row) from the source frame to the target frame."""

    source: int
    target: int
    points_px: np.ndarray
    points_world_mm: np.ndarray
    measured_px: np.ndarray
    model_px: np.ndarray  # the tracking model's (at the parameters tracking used)
    quality: np.ndarray  # normalized cross-correlation of the block after registration
    valid: np.ndarray  # blocks kept (inside the images, well correlated)
    grid_index: np.ndarray  # (n, 2) row, col of each block in the block grid

    @property
    def residual_px(self) -> np.ndarray:
        return self.measured_px - self.model_px


@dataclass(frozen=True)
class TrackedField:
    pairs: tuple[TrackedPair, ...]
    block_px: int
    noise_px: float  # tracking noise per displacement component, RMS over the pairs
    # each pair's own (a frame further from the source in strain decorrelates more)
    pair_noise_px: tuple[float, ...] = ()

    def pair_noise(self, k: int) -> float:
        """The tracking noise of pair ``k`` (the pooled one when it has none of its own)."""
        return self.pair_noise_px[k] if k < len(self.pair_noise_px) else self.noise_px

    @property
    def n_valid(self) -> int:
        return int(sum(p.valid.sum() for p in self.pairs))


def _block_match(block: np.ndarray, search: np.ndarray) -> tuple[np.ndarray, float]:
    """Where the content of ``block`` (b x b) moved to inside ``search`` ((b + 2m)^2,
    centred on it): the shift t (row, col) px with search(x + t) ~ block(x),
    from the peak of the normalized cross-correlation refined by a parabola per
    axis, and the peak value."""
    from skimage.feature import match_template

    ncc = match_template(search, block)  # (2m + 1, 2m + 1)
    m = (ncc.shape[0] - 1) // 2
    i, j = np.unravel_index(int(np.argmax(ncc)), ncc.shape)

    def vertex(a, b, c):
        den = a - 2 * b + c
        return 0.0 if den >= 0 else 0.5 * (a - c) / den

    di = vertex(ncc[i - 1, j], ncc[i, j], ncc[i + 1, j]) if 0 < i < ncc.shape[0] - 1 else 0.0
    dj = vertex(ncc[i, j - 1], ncc[i, j], ncc[i, j + 1]) if 0 < j < ncc.shape[1] - 1 else 0.0
    on_edge = i in (0, ncc.shape[0] - 1) or j in (0, ncc.shape[1] - 1)
    return np.array([i - m + di, j - m + dj]), (float(ncc[i, j]) if not on_edge else 0.0)


def robust_noise(values: np.ndarray, grid: np.ndarray) -> float:
    """Noise of values (n, k) on a block grid (n, 2 ints): MAD of second differences
    along rows and columns between valid neighbours, / sqrt(6)."""
    if len(values) < 3:
        return float("nan")
    lut = {tuple(g): i for i, g in enumerate(grid)}
    d2 = []
    for i, (r, c) in enumerate(grid):
        for dr, dc in ((0, 1), (1, 0)):
            j, k = lut.get((r - dr, c - dc)), lut.get((r + dr, c + dc))
            if j is not None and k is not None:
                d2.append(values[j] - 2 * values[i] + values[k])
    if len(d2) < 3:
        return float("nan")
    d2 = np.asarray(d2).ravel()
    return float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / np.sqrt(6.0))


REFINE_ITERATIONS = 5  # sub-pixel refinement rounds of each block (see track)
SOURCE_ORDER = 3  # spline order sampling the source block (linear at half pixels would blur it)


def track(problem, params: dict, block_px: int | None = None, min_quality: float = 0.3) -> TrackedField:
    """Model-assisted speckle tracking of every frame pair of ``problem`` with the
    model at ``params`` (see the module docstring)."""
    if block_px is None:
        # about 3 mm: enough speckles for a stable correlation peak
        block_px = int(max(16, min(32, round(3.0 / min(problem._sc, problem._sr)))))
    b = int(block_px)
    c0, r0, c1, r1 = problem.roi
    rows_c = np.arange(r0 + b // 2, r1 - b // 2 + 1, b)
    cols_c = np.arange(c0 + b // 2, c1 - b // 2 + 1, b)
    RC, CC = np.meshgrid(rows_c, cols_c, indexing="ij")
    gi = np.stack(np.meshgrid(np.arange(len(rows_c)), np.arange(len(cols_c)), indexing="ij"), -1).reshape(-1, 2)
    centres = np.column_stack([CC.ravel(), RC.ravel()]).astype(float)  # (col, row)
    offs = np.arange(b) - (b - 1) / 2.0
    params = problem.complete(params) if hasattr(problem, "complete") else params
    a = problem.rm.coords(problem.theta(params))
    pairs = []
    for pair in problem.pairs:
        src = pair.source_image
        tgt = problem.exp.image(pair.target)
        H, W = src.shape
        coarse = problem._coarse_field(pair, a)  # (len(src_rows), len(src_cols), 2) px, source grid
        step = pair.warp.step
        meas, model, qual, valid = [], [], [], []
        mrg = 4  # search margin, px
        offs_big = np.arange(b + 2 * mrg) - (b + 2 * mrg - 1) / 2.0
        for (cc, rr) in centres:
            pr = rr + offs[:, None] + 0 * offs[None, :]
            pc = cc + 0 * offs[:, None] + offs[None, :]
            S = map_coordinates(src, [pr, pc], order=SOURCE_ORDER, mode="nearest")
            # the target, sampled where the model moved each source pixel (the block plus a margin)
            br = rr + offs_big[:, None] + 0 * offs_big[None, :]
            bc = cc + 0 * offs_big[:, None] + offs_big[None, :]
            dc = map_coordinates(coarse[..., 0], [br / step, bc / step], order=1, mode="nearest")
            dr = map_coordinates(coarse[..., 1], [br / step, bc / step], order=1, mode="nearest")
            qr, qc = br + dr, bc + dc
            mdc = float(map_coordinates(coarse[..., 0], [[rr / step], [cc / step]], order=1)[0])
            mdr = float(map_coordinates(coarse[..., 1], [[rr / step], [cc / step]], order=1)[0])
            # U(p) = T(p + delta_model(p) + t_acc) holds the source block moved by
            # t = delta_true - delta_model - t_acc. A parabola through the correlation
            # peak is biased toward whole pixels (peak locking), and with model-assisted
            # sampling that pulls the measurement toward the model. Iterating until the
            # remaining shift is nil removes the bias: at zero shift it is zero.
            t_acc = np.zeros(2)
            for _ in range(REFINE_ITERATIONS):
                U = map_coordinates(tgt, [qr + t_acc[0], qc + t_acc[1]], order=3, mode="nearest")
                t, ncc = _block_match(S, U)
                t_acc = t_acc + t
                if np.abs(t).max() < 0.01 or np.abs(t_acc).max() > mrg:
                    break
            qr_f, qc_f = qr + t_acc[0], qc + t_acc[1]
            inside = (qr_f.min() >= 1) and (qr_f.max() <= H - 2) and (qc_f.min() >= 1) and (qc_f.max() <= W - 2)
            inside = inside and np.abs(t_acc).max() <= mrg
            meas.append([mdc + t_acc[1], mdr + t_acc[0]])
            model.append([mdc, mdr])
            qual.append(ncc)
            valid.append(inside and ncc >= min_quality)
        d0 = problem.exp.frames[pair.source].displacement_mm
        world = pixel_to_world(centres[:, 0], centres[:, 1], problem.exp, d0)
        pairs.append(TrackedPair(pair.source, pair.target, centres, world, np.array(meas), np.array(model),
                                 np.array(qual), np.array(valid, bool), gi))
    res = [p.residual_px[p.valid] for p in pairs]
    grids = [p.grid_index[p.valid] for p in pairs]
    sig = [robust_noise(r, g) for r, g in zip(res, grids)]
    known = [s for s in sig if np.isfinite(s)]
    noise = max(float(np.sqrt(np.mean(np.square(known)))) if known else 0.25, 0.02)
    # a pair too small to estimate its own noise takes the pooled estimate
    per_pair = tuple(max(s, 0.02) if np.isfinite(s) else noise for s in sig)
    return TrackedField(tuple(pairs), b, noise, per_pair)


# ---------------------------------------------------------------------------
# the comparison a person looks at
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class FrameComparison:
    """One target frame against the model."""

    source: int
    target: int
    time_s: float
    displacement_mm: float
    roi_px: tuple  # col0, row0, col1, row1
    warped_source: np.ndarray  # ROI
    target_roi: np.ndarray
    residual_map: np.ndarray  # 1 - local NCC on the ROI (NaN where the source did not image)
    points_px: np.ndarray  # tracked block centres (source frame pixels)
    measured_px: np.ndarray  # tracked displacement
    model_px: np.ndarray  # model displacement at the same points
    valid: np.ndarray
    region_share: dict  # region -> share of this frame's displacement misfit

    @property
    def difference_px(self) -> np.ndarray:
        """measured - model (the vector map)."""
        return self.measured_px - self.model_px


@dataclass(frozen=True)
class Comparison:
    effects: tuple
    parameters: dict
    time_s: np.ndarray
    displacement_mm: np.ndarray
    force_measured_N: np.ndarray
    force_model_N: np.ndarray
    frames: tuple[FrameComparison, ...]
    region_share: dict  # region -> share of the whole displacement misfit (sums to 1)
    image_region_share: dict  # region -> share of the residual-map misfit
    force_rms_N: float
    displacement_rms_px: float
    noise_px: float
    force_noise_N: float

    def lines(self) -> list[str]:
        out = [f"force misfit {self.force_rms_N:.4f} N RMS (noise {self.force_noise_N:.4f} N)",
               f"displacement misfit {self.displacement_rms_px:.3f} px RMS (tracking noise {self.noise_px:.3f} px)"]
        out.append("share of the displacement misfit: " + ", ".join(
            f"{k} {100 * v:.0f}%" for k, v in self.region_share.items()))
        return out


def region_labels(problem, world_mm: np.ndarray) -> np.ndarray:
    from app.core.geometry import paint_labels

    return paint_labels(np.asarray(world_mm, float), problem.exp.specimen.regions)


def compare(problem, params: dict, tracked: TrackedField | None = None, window: int = 15) -> Comparison:
    """Everything the model check view shows, for the model ``problem`` at ``params``.

    ``tracked`` (a :class:`TrackedField`, e.g. from the baseline) supplies the
    measured displacements; the model's are evaluated at the same points."""
    params = problem.complete(params) if hasattr(problem, "complete") else params
    if tracked is None:
        tracked = track(problem, params)
    a = problem.rm.coords(problem.theta(params))
    names = problem.exp.specimen.region_names
    frames = []
    tot = {n: 0.0 for n in names}
    img_tot = {n: 0.0 for n in names}
    all_res = []
    for pair, tp in zip(problem.pairs, tracked.pairs):
        w = pair.warp(pair.source_image, coarse=problem._coarse_field(pair, a))
        ls = local_similarity(w, pair.target_roi, window)
        resid = np.where(pair.mask, 1.0 - ls, np.nan)
        model = _model_at(problem, params, a, pair, tp.points_world_mm)
        diff = tp.measured_px - model
        lab = region_labels(problem, tp.points_world_mm)
        e2 = np.where(tp.valid, (diff**2).sum(1), 0.0)
        share = {n: float(e2[lab == k].sum()) for k, n in enumerate(names)}
        s = sum(share.values()) or 1.0
        for n in names:
            tot[n] += share[n]
        # residual map share by region (ROI pixels mapped to the target frame's plane)
        c0, r0, c1, r1 = problem.roi
        R, C = np.mgrid[r0:r1, c0:c1]
        step = 4
        wpts = pixel_to_world(C[::step, ::step].ravel(), R[::step, ::step].ravel(), problem.exp, pair.d_target_mm)
        lab_px = region_labels(problem, wpts)
        rr = np.nan_to_num(resid[::step, ::step].ravel(), nan=0.0)
        for k, n in enumerate(names):
            img_tot[n] += float(rr[lab_px == k].sum())
        all_res.append(diff[tp.valid])
        f = problem.exp.frames[pair.target]
        frames.append(FrameComparison(pair.source, pair.target, f.time_s, f.displacement_mm, tuple(problem.roi), w,
                                      pair.target_roi, resid, tp.points_px, tp.measured_px, model, tp.valid,
                                      {n: v / s for n, v in share.items()}))
    s = sum(tot.values()) or 1.0
    si = sum(img_tot.values()) or 1.0
    allr = np.vstack(all_res) if all_res else np.zeros((0, 2))
    Fm = problem.model_force_N(params, a)
    log = problem.exp.force_log
    return Comparison(tuple(getattr(problem, "effects", ())), dict(params), np.asarray(log.time_s),
                      np.asarray(log.displacement_mm), np.asarray(log.force_N), Fm, tuple(frames),
                      {n: v / s for n, v in tot.items()}, {n: v / si for n, v in img_tot.items()},
                      float(np.sqrt(np.mean((Fm - log.force_N) ** 2))),
                      float(np.sqrt(np.mean((allr**2).sum(1)))) if len(allr) else float("nan"),
                      tracked.noise_px, float(problem.force_sigma_N))


def _model_at(problem, params, a, pair, world):
    key = f"__cmp_{pair.target}"
    if hasattr(problem, "add_points"):
        if key not in problem._points:
            problem.add_points(key, world)
        return problem.displacement_px(params, key, pair, a)
    op = problem.rm.point_operator(world)
    u = op.values(a)
    dd = pair.d_target_mm - pair.d_source_mm
    return dd * np.column_stack([u @ problem._lat / problem._sc, (-1.0 - u[:, 2]) / problem._sr])
