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
to first order.

Speckle decorrelates under strain (scatterers inside a resolution cell move
relative to each other by a fraction of a wavelength), so a block matched
between the source frame and a frame pressed much further correlates poorly,
and a poor correlation peak can lie anywhere in the search window. Tracking is
therefore chained: each pair after the first matches each block as it looked
in the previous pair's target frame, at the pixels where that pair placed it,
so template and target are one strain step apart. On a 30 mm phantom pressed
5 mm (frames at 2.5 and 5 mm), tracked with the true model on speckle that
follows the tissue, this raised the median block correlation of the deeper
frame from 0.44 to 0.62, the blocks kept from 43 to 62, and brought its smooth
residual from 0.68 to 0.14 px.

Where the strain of one step is large (just under the probe, with the paper's
three frames 7.4 mm apart) most blocks correlate at 0.2-0.3, and some of
those that pass the 0.3 threshold have locked onto a wrong peak, several
pixels off, side by side. A block that correlates below WEAK_QUALITY (0.45)
is therefore matched again as a block twice its size about the same centre,
and kept only when that one moves with it (within CONFIRM_TOLERANCE_PX). A
true but weak peak holds over the larger block; a wrong one does not. On the
paper's phantom with a hidden Poisson's ratio of 0.4 (seed 14104) every block
that was more than 1 px off the truth's field was one the larger block did not
confirm, and the RMS of the 3 x 3 medians of the truth's residual fell from
0.61 to 0.15 px (docs/model-check.md, "Weak blocks confirmed by a larger
block").

Blocks tile the ROI without overlap, so their errors are independent. Each
block's tracking noise is its pair's scale times a decorrelation factor
sqrt(1/rho^2 - 1) of its correlation rho (the Cramer-Rao bound of speckle
tracking), and the scale is estimated from the blocks themselves (the scatter
of second differences across neighbouring blocks, each divided by its own
factor, which a smooth misfit does not reach).

A speckle match can still go wrong (a decorrelated block under the probe's
edge finds a spurious peak); its difference then disagrees with its
neighbours', which a misfit of the model would not. :func:`outliers` flags such
blocks by the normalized median test; the comparison leaves them out of the
regions' shares and the window draws them apart. The diagnosis keeps every
block: its image term is robust by itself (a Huber loss, 3 x 3 medians).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.ndimage import map_coordinates

from app.core.images import pixel_to_world, world_to_pixel
from app.core.similarity import local_similarity
from app.core.warp import bilinear


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
    # tracking noise of each block (px per component): the pair's scale times
    # the block's decorrelation factor (see block_noise); None: the pair's noise
    sigma_px: np.ndarray | None = None

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


DECORRELATION_FLOOR = 0.2  # the factor of a block correlating at 0.98 or better


def decorrelation_factor(quality: np.ndarray) -> np.ndarray:
    """How a block's tracking noise grows as its speckle decorrelates: the
    Cramer-Rao bound of speckle tracking (Walker and Trahey 1995) is proportional
    to sqrt(1 / rho^2 - 1) for a correlation rho between the matched blocks,
    3.5 times larger at rho = 0.44 than at 0.9. Floored at DECORRELATION_FLOOR."""
    rho = np.clip(np.asarray(quality, float), 0.05, 0.999)
    return np.maximum(np.sqrt(1.0 / rho**2 - 1.0), DECORRELATION_FLOOR)


def block_noise(residual: np.ndarray, grid: np.ndarray, factor: np.ndarray) -> float:
    """The scale s of a pair's tracking noise, sigma_i = s * factor_i, from the
    residual (n, k) of its valid blocks: the MAD of second differences across
    neighbouring blocks, each divided by its own standard deviation in units of s
    (sqrt(f_j^2 + 4 f_i^2 + f_k^2)). NaN when there are too few."""
    if len(residual) < 3:
        return float("nan")
    lut = {tuple(g): i for i, g in enumerate(grid)}
    d2 = []
    for i, (r, c) in enumerate(grid):
        for dr, dc in ((0, 1), (1, 0)):
            j, k = lut.get((r - dr, c - dc)), lut.get((r + dr, c + dc))
            if j is not None and k is not None:
                sd = math.sqrt(factor[j] ** 2 + 4 * factor[i] ** 2 + factor[k] ** 2)
                d2.append((residual[j] - 2 * residual[i] + residual[k]) / sd)
    if len(d2) < 3:
        return float("nan")
    d2 = np.asarray(d2).ravel()
    return float(1.4826 * np.median(np.abs(d2 - np.median(d2))))


REFINE_ITERATIONS = 5  # sub-pixel refinement rounds of each block (see track)
# A block that correlates below WEAK_QUALITY is kept only when a block twice its
# size about the same centre, matched the same way, moves by the same amount
# (within CONFIRM_TOLERANCE_PX per component): see track
WEAK_QUALITY = 0.45
CONFIRM_TOLERANCE_PX = 1.0
SOURCE_ORDER = 3  # spline order sampling the source block (linear at half pixels would blur it)


def track(problem, params: dict, block_px: int | None = None, min_quality: float = 0.3,
          chain: bool = True, confirm_weak: bool = True) -> TrackedField:
    """Model-assisted speckle tracking of every frame pair of ``problem`` with the
    model at ``params`` (see the module docstring). With ``chain``, each pair after
    the first matches each block as it looked in the previous pair's target frame
    (frames in the problem's order), where it was found there; a block the
    previous pair lost is matched from the source frame. With ``confirm_weak``, a
    block correlating below WEAK_QUALITY is kept only if a block twice its size
    about the same centre confirms its displacement (within CONFIRM_TOLERANCE_PX)."""
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
    params = problem.complete(params) if hasattr(problem, "complete") else params
    a = problem.rm.coords(problem.theta(params))
    pairs = []
    prev = None  # the previous pair's target frame, its model field, and where each block lay in it
    mrg = 4  # search margin, px
    for pair in problem.pairs:
        src = pair.source_image
        tgt = problem.exp.image(pair.target)
        H, W = src.shape
        coarse = problem._coarse_field(pair, a)  # (len(src_rows), len(src_cols), 2) px, source grid
        step = pair.warp.step
        meas, model, qual, valid, placed, shifts = [], [], [], [], [], []

        def match(cc, rr, size, ib):
            """Match the block of ``size`` px centred at (cc, rr): (measured, model,
            ncc, inside, positions of its pixels in the target, shift)."""
            offs_s = np.arange(size) - (size - 1) / 2.0
            offs_big = np.arange(size + 2 * mrg) - (size + 2 * mrg - 1) / 2.0
            pr = rr + offs_s[:, None] + 0 * offs_s[None, :]  # the block's source pixels
            pc = cc + 0 * offs_s[:, None] + offs_s[None, :]
            t_start = np.zeros(2)
            if chain and prev is not None and prev[3][ib]:
                # through the previous frame: the block as it looked there (its pixels
                # where the previous pair placed them), so the template and the target
                # are one strain step apart instead of the whole travel
                prev_img, prev_coarse, prev_pos, _, prev_t = prev
                if size == b:
                    pos = prev_pos[ib]
                else:  # a larger block: where the previous pair's model and shift put its pixels
                    pos = [pr + map_coordinates(prev_coarse[..., 1], [pr / step, pc / step], order=1, mode="nearest")
                           + prev_t[ib][0],
                           pc + map_coordinates(prev_coarse[..., 0], [pr / step, pc / step], order=1, mode="nearest")
                           + prev_t[ib][1]]
                S = map_coordinates(prev_img, pos, order=SOURCE_ORDER, mode="nearest")
                t_start = prev_t[ib]
            else:
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
            t_acc = t_start.copy()
            ncc = 0.0
            for _ in range(REFINE_ITERATIONS):
                U = map_coordinates(tgt, [qr + t_acc[0], qc + t_acc[1]], order=3, mode="nearest")
                t, ncc = _block_match(S, U)
                t_acc = t_acc + t
                if np.abs(t).max() < 0.01 or np.abs(t_acc - t_start).max() > mrg:
                    break
            qr_f, qc_f = qr + t_acc[0], qc + t_acc[1]
            inside = (qr_f.min() >= 1) and (qr_f.max() <= H - 2) and (qc_f.min() >= 1) and (qc_f.max() <= W - 2)
            inside = inside and np.abs(t_acc - t_start).max() <= mrg
            k0 = mrg + (size - b) // 2
            core = slice(k0, k0 + b)
            return ([mdc + t_acc[1], mdr + t_acc[0]], [mdc, mdr], ncc, bool(inside),
                    np.stack([qr_f[core, core], qc_f[core, core]]), t_acc)

        for ib, (cc, rr) in enumerate(centres):
            m_px, mod_px, ncc, inside, pos, t_acc = match(cc, rr, b, ib)
            if confirm_weak and inside and min_quality <= ncc < WEAK_QUALITY:
                # a weak peak must hold over a block twice the size (see the module docstring)
                big_px, _, big_ncc, big_inside, _, _ = match(cc, rr, 2 * b, ib)
                inside = big_inside and big_ncc >= min_quality and \
                    np.abs(np.subtract(big_px, m_px)).max() <= CONFIRM_TOLERANCE_PX
            meas.append(m_px)
            model.append(mod_px)
            qual.append(ncc)
            valid.append(inside and ncc >= min_quality)
            placed.append(pos)
            shifts.append(t_acc)
        prev = (tgt, coarse, placed, valid, shifts)
        d0 = problem.exp.frames[pair.source].displacement_mm
        world = pixel_to_world(centres[:, 0], centres[:, 1], problem.exp, d0)
        pairs.append(TrackedPair(pair.source, pair.target, centres, world, np.array(meas), np.array(model),
                                 np.array(qual), np.array(valid, bool), gi))
    # each block's noise: its pair's scale times its decorrelation factor, so a block
    # whose speckle decorrelated (large strain, out-of-plane motion) weighs less
    factors = [decorrelation_factor(p.quality) for p in pairs]
    scales = [block_noise(p.residual_px[p.valid], p.grid_index[p.valid], f[p.valid]) for p, f in zip(pairs, factors)]
    known = [(s, f[p.valid]) for s, f, p in zip(scales, factors, pairs) if np.isfinite(s)]
    pooled_scale = float(np.sqrt(np.mean([s * s for s, _ in known]))) if known else float("nan")
    out, per_pair = [], []
    for p, f, s in zip(pairs, factors, scales):
        if not np.isfinite(s):
            s = pooled_scale  # a pair too small to estimate its own scale takes the pooled one
        sig = np.maximum(s * f, 0.02) if np.isfinite(s) else np.full(len(f), 0.25)
        out.append(replace(p, sigma_px=sig))
        per_pair.append(float(np.sqrt(np.mean(sig[p.valid] ** 2))) if p.valid.any() else 0.25)
    noise = float(np.sqrt(np.mean(np.square(per_pair)))) if per_pair else 0.25
    return TrackedField(tuple(out), b, noise, tuple(per_pair))


# ---------------------------------------------------------------------------
# the comparison a person looks at
# ---------------------------------------------------------------------------


_NEIGHBOURHOODS: dict = {}


def neighbourhoods(valid: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """For each valid block (in index order), the indices of the valid blocks in its
    3 x 3 neighbourhood, itself included: (n_valid, 9), -1 where there is none.
    Depends only on which blocks are valid, so it is built once per tracked pair
    (the fits of a diagnosis evaluate the misfit thousands of times)."""
    key = (np.asarray(valid, bool).tobytes(), np.asarray(grid).tobytes())
    idx = _NEIGHBOURHOODS.get(key)
    if idx is None:
        lut = {tuple(g): i for i, g in enumerate(grid) if valid[i]}
        rows = []
        for i, (r, cc) in enumerate(grid):
            if valid[i]:
                rows.append([lut.get((r + dr, cc + dc), -1) for dr in (-1, 0, 1) for dc in (-1, 0, 1)])
        idx = np.asarray(rows, int).reshape(-1, 9)
        if len(_NEIGHBOURHOODS) > 256:
            _NEIGHBOURHOODS.clear()
        _NEIGHBOURHOODS[key] = idx
    return idx


def gather(values: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """values[idx] with NaN where idx is -1: (n_valid, 9, ...)."""
    v = np.asarray(values, float)[np.where(idx >= 0, idx, 0)]
    v[idx < 0] = np.nan  # a (n, 9) mask selects whole trailing rows
    return v


def neighbour_median(v: np.ndarray) -> np.ndarray:
    """``np.nanmedian(v, axis=1)`` of gathered neighbourhoods (n, 9, ...), NaN where a
    row has no value. numpy takes a masked-array path for such short axes, about 5x
    slower; a diagnosis' fits take these medians thousands of times."""
    s = np.sort(v, axis=1)  # NaNs sort last
    k = (~np.isnan(v)).sum(axis=1, keepdims=True)
    lo = np.take_along_axis(s, np.maximum((k - 1) // 2, 0), axis=1)
    hi = np.take_along_axis(s, k // 2, axis=1)
    med = ((lo + hi) / 2)[:, 0]
    med[k[:, 0] == 0] = np.nan
    return med


OUTLIER_THRESHOLD = 3.0  # normalized median residual above which a block is a tracking outlier
OUTLIER_MIN_NEIGHBOURS = 4  # a median of fewer valid neighbours is too unsure to judge a block by


def outliers(diff_px: np.ndarray, valid: np.ndarray, grid: np.ndarray, eps_px: float) -> np.ndarray:
    """Valid blocks whose difference (measured - model) disagrees with their
    neighbours': the normalized median test of particle image velocimetry
    (Westerweel and Scarano 2005, Exp. Fluids 39: 1096). Per component, the
    distance to the median of the valid 3 x 3 neighbours (itself excluded),
    divided by their median distance to it plus ``eps_px`` (the tracking noise);
    above OUTLIER_THRESHOLD in either component the block is an outlier, a
    speckle match gone wrong rather than a misfit of the model, which its
    neighbours would share. Blocks with fewer than OUTLIER_MIN_NEIGHBOURS valid
    neighbours (a corner) are kept.
    Returns an (n,) bool mask."""
    valid = np.asarray(valid, bool)
    out = np.zeros(len(valid), bool)
    idx = neighbourhoods(valid, grid).copy()
    if len(idx) == 0:
        return out
    idx[:, 4] = -1  # the block itself
    nb = gather(diff_px, idx)  # (n_valid, 9, 2)
    med = neighbour_median(nb)  # NaN for a block without valid neighbours
    spread = neighbour_median(np.abs(nb - med[:, None, :]))
    r = np.abs(np.asarray(diff_px, float)[valid] - med) / (spread + eps_px)
    enough = (idx >= 0).sum(axis=1) >= OUTLIER_MIN_NEIGHBOURS
    out[np.flatnonzero(valid)] = enough & (np.nan_to_num(r, nan=0.0).max(axis=1) > OUTLIER_THRESHOLD)
    return out


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
    region_share: dict  # region -> share of this frame's displacement misfit (outliers left out)
    outlier: np.ndarray  # valid blocks that fail the normalized median test (see outliers)
    source_displacement_mm: float = 0.0  # the source frame's probe travel
    # where every OUTLINE_STEP_PX-th pixel of the target ROI came from in the source
    # frame, by the model: (rows, cols, 2) of (col, row) px (see outlines)
    source_of_target_px: np.ndarray | None = None
    # the model's regions outlined (see outlines): {"source": {...}, "target": {...}}, made
    # with the comparison, on the worker thread (a region read from a surface file
    # takes seconds: a winding number per grid point)
    region_outlines: dict = field(default_factory=dict)

    @property
    def difference_px(self) -> np.ndarray:
        """measured - model (the vector map)."""
        return self.measured_px - self.model_px

    @property
    def kept(self) -> np.ndarray:
        """The valid blocks that are not tracking outliers (what the shares count)."""
        return np.asarray(self.valid, bool) & ~np.asarray(self.outlier, bool)

    @property
    def difference_rms_px(self) -> float:
        """RMS of the difference over the kept blocks (NaN when none is kept)."""
        d = np.asarray(self.difference_px, float)[self.kept]
        return float(np.sqrt(np.mean((d**2).sum(1)))) if len(d) else math.nan


@dataclass(frozen=True)
class Comparison:
    effects: tuple
    parameters: dict
    time_s: np.ndarray
    displacement_mm: np.ndarray
    force_measured_N: np.ndarray
    force_model_N: np.ndarray
    frames: tuple[FrameComparison, ...]
    region_share: dict  # region -> share of the whole displacement misfit (sums to 1; outliers left out)
    image_region_share: dict  # region -> share of the residual-map misfit
    force_rms_N: float
    displacement_rms_px: float
    noise_px: float
    force_noise_N: float
    regions: tuple = ()  # the model's regions (app.core.geometry.Region), an added inclusion among them
    experiment: object = field(default=None, repr=False)  # the experiment compared (its imaging geometry)

    def outlines(self, k: int, regions=None, frame: str = "target") -> dict[str, list[np.ndarray]]:
        """:func:`outlines` on frame ``k`` of the comparison; by default of the model's regions."""
        if regions is None and frame in self.frames[k].region_outlines:
            return self.frames[k].region_outlines[frame]
        return outlines(self.experiment, self.frames[k], self.regions if regions is None else regions, frame)

    def outside_text(self, k: int, region) -> str:
        """:func:`outside_text` for frame ``k``."""
        return outside_text(self.experiment, self.frames[k], region)

    def lines(self) -> list[str]:
        out = [f"force misfit {self.force_rms_N:.4f} N RMS (noise {self.force_noise_N:.4f} N)",
               f"displacement misfit {self.displacement_rms_px:.3f} px RMS (tracking noise {self.noise_px:.3f} px)"]
        out.append("share of the displacement misfit: " + ", ".join(
            f"{k} {100 * v:.0f}%" for k, v in self.region_share.items()))
        n_out = sum(int(np.sum(f.outlier)) for f in self.frames)
        if n_out:
            n_valid = sum(int(np.sum(f.valid)) for f in self.frames)
            out.append(f"{n_out} of {n_valid} tracked blocks disagree with their neighbours (tracking outliers, "
                       "left out of the shares)")
        return out


def region_labels(problem, world_mm: np.ndarray) -> np.ndarray:
    from app.core.geometry import paint_labels

    return paint_labels(np.asarray(world_mm, float), problem.exp.specimen.regions)


def residual_map_labels(problem, source_px: np.ndarray, d_source_mm: float) -> np.ndarray:
    """The region of each residual-map pixel whose source position (``source_px``:
    (..., 2) of (col, row), where the model's warp samples the source frame for it;
    FrameComparison.source_of_target_px) is given: the region of that material point,
    placed in the source frame at the probe's travel ``d_source_mm``. Labelling the
    pressed frame's pixels where they lie instead took the tissue the probe had
    pushed up into the image for what lay there before: at 5 mm of travel on the
    test phantom, a 13.5 px rise of A's outline (tests/core/test_compare.py)."""
    pts = np.asarray(source_px, float)
    world = pixel_to_world(pts[..., 0].ravel(), pts[..., 1].ravel(), problem.exp, d_source_mm)
    return region_labels(problem, world).reshape(pts.shape[:-1])


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
    for k_pair, (pair, tp) in enumerate(zip(problem.pairs, tracked.pairs)):
        rows_src, cols_src = pair.warp.sample_positions(coarse=problem._coarse_field(pair, a))
        w = bilinear(np.asarray(pair.source_image, float), rows_src, cols_src)
        st = OUTLINE_STEP_PX
        src_of_tgt = np.stack([cols_src[::st, ::st], rows_src[::st, ::st]], axis=-1)
        ls = local_similarity(w, pair.target_roi, window)
        resid = np.where(pair.mask, 1.0 - ls, np.nan)
        model = _model_at(problem, params, a, pair, tp.points_world_mm)
        diff = tp.measured_px - model
        lab = region_labels(problem, tp.points_world_mm)
        # a single wrong speckle match can hold most of a region's squared misfit: the
        # shares leave the outliers out (the RMS misfit keeps them, as the diagnosis does)
        out = outliers(diff, tp.valid, tp.grid_index, max(0.05, tracked.pair_noise(k_pair)))
        e2 = np.where(tp.valid & ~out, (diff**2).sum(1), 0.0)
        share = {n: float(e2[lab == k].sum()) for k, n in enumerate(names)}
        s = sum(share.values()) or 1.0
        for n in names:
            tot[n] += share[n]
        # residual map share by region: every 2 st-th ROI pixel, by the region of the material
        # point the model brings there (see residual_map_labels)
        lab_px = residual_map_labels(problem, src_of_tgt[::2, ::2], pair.d_source_mm)
        rr = np.nan_to_num(resid[:: 2 * st, :: 2 * st], nan=0.0)
        for k, n in enumerate(names):
            img_tot[n] += float(rr[lab_px == k].sum())
        all_res.append(diff[tp.valid])
        f = problem.exp.frames[pair.target]
        fc = FrameComparison(pair.source, pair.target, f.time_s, f.displacement_mm, tuple(problem.roi), w,
                             pair.target_roi, resid, tp.points_px, tp.measured_px, model, tp.valid,
                             {n: v / s for n, v in share.items()}, out, pair.d_source_mm, src_of_tgt)
        regions = problem.exp.specimen.regions
        frames.append(replace(fc, region_outlines={side: outlines(problem.exp, fc, regions, side)
                                                   for side in ("source", "target")}))
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
                      tracked.noise_px, float(problem.force_sigma_N), tuple(problem.exp.specimen.regions), problem.exp)


# the outlines' grid: every second pixel; each outline point is then placed on the
# region's boundary along its grid edge by bisection (OUTLINE_BISECTIONS halvings:
# to 2/256 px)
OUTLINE_STEP_PX = 2
OUTLINE_BISECTIONS = 8


def outlines(exp, fc: FrameComparison, regions, frame: str = "target") -> dict[str, list[np.ndarray]]:
    """Where each of ``regions`` (app.core.geometry.Region; the background is
    skipped) lies in a compared frame's ROI: its outline as polylines (n, 2) of
    (col, row) pixels, by region name; a region that does not cut the image
    plane within the ROI has none.

    ``frame`` "source": the region's section by the source frame's image plane
    (the model's reference state). "target": the same material boundary where the
    model's displacement carried it in the target frame (a pixel of the target
    is inside when the source pixel the model brings to it is), so on the
    residual map the outline sits where the model puts the region: a misfit along
    it points at the region's stiffness or shape."""
    if frame not in ("source", "target"):
        raise ValueError(f"frame must be 'source' or 'target', got {frame!r}")
    from skimage.measure import find_contours

    c0, r0, c1, r1 = fc.roi_px
    st = OUTLINE_STEP_PX
    moved = frame == "target" and fc.source_of_target_px is not None
    shape = fc.source_of_target_px.shape[:2] if moved else (len(range(r0, r1, st)), len(range(c0, c1, st)))

    def material(i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """World points (source frame, the model's reference) of grid positions (i, j), fractional."""
        if moved:
            cols = map_coordinates(fc.source_of_target_px[..., 0], [i, j], order=1, mode="nearest")
            rows = map_coordinates(fc.source_of_target_px[..., 1], [i, j], order=1, mode="nearest")
        else:
            cols, rows = c0 + st * j, r0 + st * i
        return pixel_to_world(cols, rows, exp, fc.source_displacement_mm)

    I, J = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    world = material(I.ravel(), J.ravel())
    out = {}
    for region in regions:
        if region.kind == "background":
            continue
        inside = region.contains(world).reshape(shape)
        if not inside.any() or inside.all():
            continue
        lines = [ln for ln in find_contours(inside.astype(float), 0.5) if len(ln) >= 2]
        if not lines:
            continue
        # each vertex is the middle of a grid edge with one end inside, one outside:
        # bisect along that edge for where the region's boundary crosses it
        v = np.vstack(lines)
        lo, hi = np.floor(v), np.ceil(v)
        lo_in = inside[lo[:, 0].astype(int), lo[:, 1].astype(int)]
        p_in, p_out = np.where(lo_in[:, None], lo, hi), np.where(lo_in[:, None], hi, lo)
        t_in, t_out = np.zeros(len(v)), np.ones(len(v))
        for _ in range(OUTLINE_BISECTIONS):
            t = 0.5 * (t_in + t_out)
            q = p_in + t[:, None] * (p_out - p_in)
            now_in = region.contains(material(q[:, 0], q[:, 1]))
            t_in, t_out = np.where(now_in, t, t_in), np.where(now_in, t_out, t)
        q = p_in + (0.5 * (t_in + t_out))[:, None] * (p_out - p_in)
        ends = np.cumsum([len(ln) for ln in lines])[:-1]
        out[region.name] = [np.column_stack([c0 + st * g[:, 1], r0 + st * g[:, 0]]) for g in np.split(q, ends)]
    return out


def outside_text(exp, fc: FrameComparison, region) -> str:
    """Where a region that has no outline in frame ``fc``'s ROI (:func:`outlines`)
    lies, in words: "3.2 mm beside the image plane" for a sphere the plane does not
    cut; else where its centre lies from the ROI in the source image ("right of the
    ROI"), or "outside the ROI"."""
    lat = np.asarray(exp.probe.lateral_axis, float)
    normal = np.cross(lat, [0.0, 0.0, 1.0])
    origin = pixel_to_world(np.array([0.0]), np.array([0.0]), exp, fc.source_displacement_mm)[0]
    if region.kind == "sphere":
        gap = abs(float(np.dot(np.asarray(region.center_mm, float) - origin, normal))) - float(region.radius_mm)
        if gap >= 0.0:
            return f"{gap:.1f} mm beside the image plane"
    if region.center_mm is None:
        return "outside the ROI"
    cols, rows = world_to_pixel(np.asarray([region.center_mm], float), exp, fc.source_displacement_mm)
    c0, r0, c1, r1 = fc.roi_px
    sides = [w for w, beyond in (("left of", cols[0] < c0), ("right of", cols[0] >= c1), ("above", rows[0] < r0),
                                 ("below", rows[0] >= r1)) if beyond]
    return f"{' and '.join(sides)} the ROI" if sides else "outside the ROI"


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
