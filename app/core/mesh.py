"""Conforming tetrahedral meshes of a specimen with pytetwild.

The input surface holds the specimen box, whose top face is triangulated with
the probe outline as edges, and every region's closed surface, so region
interfaces and the probe face are resolved by the mesh. A background sizing
field refines the mesh under the probe. fTetWild holds the GIL for its whole
run, so it runs in a child process that can be cancelled. Meshes are cached on
disk by the hash of their inputs.
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing as mp
import os
import sys
import threading
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from app.core.errors import Cancelled, MeshingError
from app.core.geometry import Region, box_surface, paint_labels

MESH_VERSION = 7  # bump when meshing changes, to invalidate caches


@dataclass(frozen=True)
class MeshSettings:
    """Target edge lengths in mm: ``edge_mm`` far from the probe, ``probe_edge_mm``
    on the probe face; the size grows by ``grading`` mm per mm of distance."""

    edge_mm: float = 10.0
    probe_edge_mm: float = 2.5
    grading: float = 0.35
    epsilon: float = 5e-4  # fTetWild envelope, relative to the bounding box diagonal
    region_edge_mm: float | None = None  # size in and around regions (default: a fifth of their thinnest extent)

    def with_scale(self, factor: float) -> "MeshSettings":
        """Every length multiplied by ``factor`` (< 1 refines)."""
        r = None if self.region_edge_mm is None else self.region_edge_mm * factor
        return MeshSettings(self.edge_mm * factor, self.probe_edge_mm * factor, self.grading, self.epsilon, r)


@dataclass(frozen=True)
class TetMesh:
    """Linear tetrahedra (points mm, tets as vertex indices) with a region label per tet."""

    points_mm: np.ndarray
    tets: np.ndarray
    labels: np.ndarray
    region_names: tuple[str, ...]
    size_mm: tuple[float, float, float]
    probe_rect_mm: tuple[float, float, float, float]

    @property
    def n_nodes(self) -> int:
        return len(self.points_mm)

    @property
    def n_tets(self) -> int:
        return len(self.tets)

    def tet_volumes_mm3(self) -> np.ndarray:
        p = self.points_mm[self.tets]
        return np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6.0

    def top_nodes(self, tol: float = 1e-6) -> np.ndarray:
        return np.abs(self.points_mm[:, 2] - self.size_mm[2]) < tol

    def probe_nodes(self, points: np.ndarray | None = None, tol: float = 1e-6) -> np.ndarray:
        """Mask of points on the top face inside the probe face (outline included)."""
        p = self.points_mm if points is None else points
        return probe_face_mask(p, self.size_mm, self.probe_rect_mm, tol)


@dataclass(frozen=True)
class MeshQuality:
    n_nodes: int
    n_tets: int
    n_probe_nodes: int
    min_dihedral_deg: float
    max_dihedral_deg: float
    region_volume_mm3: dict
    region_geometric_volume_mm3: dict

    def lines(self) -> list[str]:
        out = [f"{self.n_nodes} nodes, {self.n_tets} tetrahedra, {self.n_probe_nodes} vertices on the probe face",
               f"dihedral angles {self.min_dihedral_deg:.1f} to {self.max_dihedral_deg:.1f} deg"]
        for k, v in self.region_volume_mm3.items():
            g = self.region_geometric_volume_mm3[k]
            out.append(f"region {k}: meshed {v:.0f} mm3, geometric {g:.0f} mm3 ({100 * (v - g) / g:+.1f}%)")
        return out


def quality(mesh: TetMesh, regions: tuple[Region, ...]) -> MeshQuality:
    """Counts, dihedral angle range, and each region's meshed vs geometric volume.

    A region's geometric volume is what it covers after later regions paint over it.
    """
    vol = mesh.tet_volumes_mm3()
    ang = dihedral_angles_deg(mesh.points_mm, mesh.tets)
    meshed = {n: float(vol[mesh.labels == k].sum()) for k, n in enumerate(mesh.region_names)}
    geo = {}
    box = float(np.prod(mesh.size_mm))
    for k, r in enumerate(regions):
        geo[r.name] = r.volume_mm3(mesh.size_mm)
    # the background loses what the others cover (regions assumed disjoint)
    geo[regions[0].name] = box - sum(geo[r.name] for r in regions[1:])
    return MeshQuality(mesh.n_nodes, mesh.n_tets, int(mesh.probe_nodes().sum()), float(ang.min()), float(ang.max()),
                       meshed, geo)


def dihedral_angles_deg(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """The six dihedral angles of every tetrahedron, (m, 6) degrees."""
    p = points[tets]
    faces = [(1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2)]  # face opposite vertex i
    normals = []
    for i, (a, b, c) in enumerate(faces):
        n = np.cross(p[:, b] - p[:, a], p[:, c] - p[:, a])
        # orient outward: away from the opposite vertex
        s = np.sign(np.einsum("ij,ij->i", n, p[:, a] - p[:, i]))
        normals.append(n * s[:, None] / np.linalg.norm(n, axis=1, keepdims=True))
    out = []
    for i in range(4):
        for j in range(i + 1, 4):
            cos = -np.einsum("ij,ij->i", normals[i], normals[j])
            out.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    return np.column_stack(out)


# ---------------------------------------------------------------------------
# input surface and sizing field
# ---------------------------------------------------------------------------


def _ticks(lo: float, a: float, b: float, hi: float, fine: float, coarse: float) -> np.ndarray:
    """1-D ticks on [lo, hi] that include a and b, fine inside [a, b], coarser outside."""
    parts = []
    if a > lo + 1e-9:
        parts.append(np.linspace(lo, a, max(2, int(np.ceil((a - lo) / coarse)) + 1)))
    parts.append(np.linspace(a, b, max(2, int(np.ceil((b - a) / fine)) + 1)))
    if hi > b + 1e-9:
        parts.append(np.linspace(b, hi, max(2, int(np.ceil((hi - b) / coarse)) + 1)))
    return np.unique(np.concatenate(parts))


def input_surface(size_mm, probe_rect_mm, regions: tuple[Region, ...], settings: MeshSettings):
    """Vertices and triangles fed to fTetWild: the box with the probe outline
    imprinted on its top face, plus every non-background region's surface."""
    sx, sy, sz = size_mm
    x0, x1, y0, y1 = probe_rect_mm
    fine, coarse = settings.probe_edge_mm, min(settings.edge_mm, 3 * settings.probe_edge_mm)
    top = (_ticks(0, x0, x1, sx, fine, coarse), _ticks(0, y0, y1, sy, fine, coarse))
    verts, faces = box_surface((0, 0, 0), size_mm, settings.edge_mm, top_lines=top)
    vs, fs = [verts], [faces]
    n = len(verts)
    for r in regions[1:]:
        v, f = r.surface(edge_mm=min(4.0, 0.75 * region_edge_mm(r, settings)))
        vs.append(v)
        fs.append(f + n)
        n += len(v)
    return np.vstack(vs), np.vstack(fs)


def region_edge_mm(region: Region, settings: MeshSettings) -> float:
    lo, hi = region.bounds_mm()
    own = 0.2 * float(np.min(hi - lo))
    return min(settings.edge_mm, settings.region_edge_mm or own)


def sizing_field(size_mm, probe_rect_mm, settings: MeshSettings, regions: tuple[Region, ...] = ()):
    """Background tets with the target edge length at their vertices (mm)."""
    sx, sy, sz = size_mm
    step = max(settings.probe_edge_mm, min(size_mm) / 24)
    nx, ny, nz = (max(3, int(np.ceil(s / step)) + 1) for s in size_mm)
    xs, ys, zs = np.linspace(0, sx, nx), np.linspace(0, sy, ny), np.linspace(0, sz, nz)
    X, Y, Z = np.meshgrid(xs, ys, zs, indexing="ij")
    pts = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    idx = np.arange(len(pts)).reshape(nx, ny, nz)
    # six tets per cube (Kuhn subdivision), consistent across neighbours
    c = np.stack([idx[:-1, :-1, :-1], idx[1:, :-1, :-1], idx[1:, 1:, :-1], idx[:-1, 1:, :-1],
                  idx[:-1, :-1, 1:], idx[1:, :-1, 1:], idx[1:, 1:, 1:], idx[:-1, 1:, 1:]], -1).reshape(-1, 8)
    kuhn = [(0, 1, 2, 6), (0, 2, 3, 6), (0, 3, 7, 6), (0, 7, 4, 6), (0, 4, 5, 6), (0, 5, 1, 6)]
    tets = np.concatenate([c[:, list(k)] for k in kuhn]).astype(np.int32)
    x0, x1, y0, y1 = probe_rect_mm
    dx = np.maximum(np.maximum(x0 - pts[:, 0], pts[:, 0] - x1), 0)
    dy = np.maximum(np.maximum(y0 - pts[:, 1], pts[:, 1] - y1), 0)
    dz = sz - pts[:, 2]
    h = np.minimum(settings.probe_edge_mm + settings.grading * np.sqrt(dx**2 + dy**2 + dz**2), settings.edge_mm)
    # resolve each region's strain field: small elements in and around it, graded outward
    for r in regions[1:]:
        lo, hi = r.bounds_mm()
        d = np.linalg.norm(np.maximum(np.maximum(lo - pts, pts - hi), 0.0), axis=1)
        h = np.minimum(h, region_edge_mm(r, settings) + settings.grading * d)
    return pts, tets, h


def _die_with_parent() -> None:
    """Linux: the kernel kills this child when its parent dies (a crashed or killed
    window must not leave a mesher running; pytetwild holds the GIL, so a watchdog
    thread could not do it)."""
    if sys.platform.startswith("linux"):
        try:
            import ctypes
            import signal

            ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            return
        if os.getppid() == 1:  # the parent died before the request took effect
            os._exit(1)


def _tetwild_job(args, queue):
    """Child process: run fTetWild and send the result back."""
    try:
        import tempfile

        import pytetwild

        _die_with_parent()
        # fTetWild writes __tracked_surface.stl into the working directory
        os.chdir(tempfile.mkdtemp(prefix="elastoid-tetwild-"))
        v, f, bg_v, bg_t, bg_h, edge, eps, threads = args
        V, T = pytetwild.tetrahedralize(v, f.astype(np.int32), edge_length_abs=edge, epsilon=eps,
                                        bg_vertices=bg_v, bg_tets=bg_t, bg_values=bg_h, num_threads=threads)
        queue.put(("ok", np.asarray(V, float), np.asarray(T, np.int64)))
    except BaseException as exc:  # report anything to the parent
        queue.put(("error", repr(exc), None))


def _mesh_key(size_mm, probe_rect_mm, regions, settings) -> str:
    def reg(r: Region):
        d = {k: v for k, v in asdict(r).items() if k not in ("surface_mesh", "file")}
        if r.surface_mesh is not None:
            d["surface"] = hashlib.sha1(np.ascontiguousarray(r.surface_mesh[0]).tobytes()
                                        + np.ascontiguousarray(r.surface_mesh[1]).tobytes()).hexdigest()
        return d

    blob = json.dumps({"v": MESH_VERSION, "size": list(size_mm), "probe": list(probe_rect_mm),
                       "regions": [reg(r) for r in regions], "settings": asdict(settings)},
                      sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:24]


def cache_dir() -> Path:
    d = Path(os.environ.get("ELASTOID_CACHE_DIR", Path.home() / ".cache" / "elastoid")) / "meshes"
    d.mkdir(parents=True, exist_ok=True)
    return d


def _tetwild(args, cancel: threading.Event | None, timeout_s: float):
    """Run fTetWild on ``args`` in a child process; (V, T), or MeshingError/Cancelled."""
    import queue as _q
    import time

    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=_tetwild_job, args=(args, queue), daemon=True)
    proc.start()
    t0 = time.monotonic()
    result = None
    try:
        while result is None:
            if cancel is not None and cancel.is_set():
                raise Cancelled("meshing cancelled")
            try:
                result = queue.get(timeout=0.1)
            except _q.Empty:
                if not proc.is_alive():
                    raise MeshingError(f"the mesher stopped unexpectedly (exit code {proc.exitcode})") from None
                if time.monotonic() - t0 > timeout_s:
                    raise MeshingError(f"meshing took longer than {timeout_s:.0f} s") from None
    finally:
        if proc.is_alive():
            proc.terminate()
        proc.join(timeout=5)
    status, V, T = result
    if status != "ok":
        raise MeshingError(f"fTetWild failed: {V}")
    return V, T


def build_mesh(size_mm, probe_rect_mm, regions: tuple[Region, ...], settings: MeshSettings = MeshSettings(),
               *, progress: Callable[[str], None] | None = None, cancel: threading.Event | None = None,
               use_cache: bool = True, timeout_s: float = 600.0) -> TetMesh:
    """Mesh the specimen box with its regions; refined under the probe face.

    Runs fTetWild in a child process; ``cancel`` (a threading.Event) stops it.
    """
    size_mm = tuple(float(s) for s in size_mm)
    key = _mesh_key(size_mm, probe_rect_mm, regions, settings)
    path = cache_dir() / f"{key}.npz"
    names = tuple(r.name for r in regions)
    if use_cache and path.is_file():
        try:
            d = np.load(path)
            if progress:
                progress("mesh loaded from cache")
            return TetMesh(d["points"], d["tets"], d["labels"], names, size_mm, tuple(probe_rect_mm))
        except (OSError, ValueError, KeyError):
            path.unlink(missing_ok=True)
    v, f = input_surface(size_mm, probe_rect_mm, regions, settings)
    bg_v, bg_t, bg_h = sizing_field(size_mm, probe_rect_mm, settings, regions)
    if progress:
        progress(f"meshing: {len(f)} input triangles")
    # one thread: fTetWild's multi-threaded runs differ from run to run, and a
    # scientific result must not depend on thread timing
    threads = int(os.environ.get("ELASTOID_MESH_THREADS", "1"))
    args = (v, f, bg_v, bg_t, bg_h, settings.edge_mm, settings.epsilon, threads)
    # fTetWild sometimes loses part of the imprinted probe outline (a face edge
    # with no vertex within snapping reach): mesh again, up to three times
    for attempt in range(3):
        V, T = _tetwild(args, cancel, timeout_s)
        V, T = _orient_and_clean(V, T)
        V = snap_to_probe_outline(V, T, size_mm, probe_rect_mm, 0.4 * settings.probe_edge_mm)
        if _outline_resolved(V, size_mm, probe_rect_mm) or attempt == 2:
            break
        if progress:
            progress("the mesh lost part of the probe face outline; meshing again")
    labels = paint_labels(V[T].mean(axis=1), regions)
    mesh = TetMesh(V, T, labels, names, size_mm, tuple(probe_rect_mm))
    missing = [n for k, n in enumerate(names) if not np.any(labels == k)]
    if missing:
        raise MeshingError(f"region(s) {', '.join(missing)} received no elements; refine the mesh (smaller edge_mm)")
    if use_cache:
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, points=V, tets=T, labels=labels)
        os.replace(tmp, path)
    if progress:
        progress(f"mesh: {mesh.n_nodes} nodes, {mesh.n_tets} tetrahedra")
    return mesh


def probe_face_mask(p: np.ndarray, size_mm, rect, tol: float = 1e-6) -> np.ndarray:
    """Mask of points on the top face inside the probe face (outline included)."""
    x0, x1, y0, y1 = rect
    return (np.abs(p[:, 2] - size_mm[2]) < tol) & (p[:, 0] >= x0 - tol) & (p[:, 0] <= x1 + tol) \
        & (p[:, 1] >= y0 - tol) & (p[:, 1] <= y1 + tol)


def _outline_resolved(V: np.ndarray, size_mm, rect, tol: float = 1e-6) -> bool:
    """Whether vertices on the top face lie on all four edges of the probe face."""
    x0, x1, y0, y1 = rect
    p = V[probe_face_mask(V, size_mm, rect, tol)]
    if len(p) == 0:
        return False
    return bool(np.isclose(p[:, 0].min(), x0) and np.isclose(p[:, 0].max(), x1)
                and np.isclose(p[:, 1].min(), y0) and np.isclose(p[:, 1].max(), y1))


def snap_to_probe_outline(V: np.ndarray, T: np.ndarray, size_mm, rect, tol: float) -> np.ndarray:
    """Move top-face vertices lying within ``tol`` of the probe outline onto it, so the
    face is meshed exactly; a move that would flatten or invert a tet is undone."""
    sz = size_mm[2]
    x0, x1, y0, y1 = rect
    V = V.copy()
    top = np.flatnonzero(np.abs(V[:, 2] - sz) < 1e-6)
    moved = {}
    for axis, lines, other, (lo, hi) in ((0, (x0, x1), 1, (y0, y1)), (1, (y0, y1), 0, (x0, x1))):
        for line in lines:
            p = V[top]
            near = (np.abs(p[:, axis] - line) < tol) & (p[:, other] > lo - tol) & (p[:, other] < hi + tol)
            for i in top[near]:
                moved.setdefault(i, V[i].copy())
                V[i, axis] = line
    if not moved:
        return V
    ids = np.fromiter(moved, int)
    inc = np.flatnonzero(np.isin(T, ids).any(axis=1))
    for _ in range(5):
        p = V[T[inc]]
        vol = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])
        bad = inc[vol <= 1e-3 * np.median(np.abs(vol))]
        if len(bad) == 0:
            break
        for i in np.intersect1d(np.unique(T[bad]), ids):
            V[i] = moved[i]
    return V


def _orient_and_clean(V: np.ndarray, T: np.ndarray):
    """Positive orientation for every tet; drop unused vertices; snap box faces."""
    p = V[T]
    vol = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])
    T = T.copy()
    neg = vol < 0
    T[neg, 1], T[neg, 2] = T[neg, 2].copy(), T[neg, 1].copy()
    T = T[np.abs(vol) > 1e-12]
    used = np.unique(T)
    remap = -np.ones(len(V), np.int64)
    remap[used] = np.arange(len(used))
    return V[used], remap[T]


def auto_settings(size_mm, probe_rect_mm, regions: tuple[Region, ...]) -> MeshSettings:
    """Edge lengths that resolve the specimen's features: at most 10 mm, an eighth of
    the smallest box side, and a third of the thinnest region, but no less than a
    tenth of the smallest side (a small region is resolved by the local
    refinement around it, not by refining the whole specimen: a 3 mm sphere
    otherwise made a million unknowns); a fifth of the probe face's short side
    (at most 2.5 mm) on the probe; inside and around each region a fifth of its
    thinnest extent (see :func:`region_edge_mm`)."""
    edge = min(10.0, min(size_mm) / 8.0)
    for r in regions[1:]:
        lo, hi = r.bounds_mm()
        edge = min(edge, max(float(np.min(hi - lo)) / 3.0, min(size_mm) / 10.0))
    x0, x1, y0, y1 = probe_rect_mm
    probe = min(2.5, min(x1 - x0, y1 - y0) / 5.0, edge)
    return MeshSettings(edge_mm=round(edge, 3), probe_edge_mm=round(probe, 3))


def specimen_mesh(exp, settings: MeshSettings | None = None, **kw) -> TetMesh:
    """Mesh of an experiment's specimen under its probe (automatic sizes by default)."""
    rect = exp.probe.face_rect_mm()
    if settings is None:
        settings = auto_settings(exp.specimen.size_mm, rect, exp.specimen.regions)
    return build_mesh(exp.specimen.size_mm, rect, exp.specimen.regions, settings, **kw)
