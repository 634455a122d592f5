"""Specimen geometry: the box and the regions painted into it.

Lengths in millimetres. Regions are painted in order: the first is the
background and fills the specimen; each later one overwrites what it covers.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

REGION_KINDS = ("background", "sphere", "box", "cylinder", "ellipsoid", "surface")


@dataclass(frozen=True)
class Region:
    """One painted region. Unused fields stay ``None`` for a given ``kind``."""

    name: str
    kind: str
    center_mm: tuple[float, float, float] | None = None
    radius_mm: float | None = None
    size_mm: tuple[float, float, float] | None = None
    height_mm: float | None = None
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    radii_mm: tuple[float, float, float] | None = None
    file: str | None = None
    # Loaded surface (vertices mm, triangles) for kind == "surface".
    surface_mesh: tuple[np.ndarray, np.ndarray] | None = field(default=None, compare=False, repr=False)

    def with_center(self, center_mm) -> "Region":
        return replace(self, center_mm=tuple(float(c) for c in center_mm))

    # ---- geometry -------------------------------------------------------
    def contains(self, points_mm: np.ndarray) -> np.ndarray:
        """Boolean mask of the points (n, 3) inside the region."""
        p = np.asarray(points_mm, float)
        if self.kind == "background":
            return np.ones(len(p), bool)
        c = np.asarray(self.center_mm, float) if self.center_mm is not None else None
        if self.kind == "sphere":
            return np.einsum("ij,ij->i", p - c, p - c) <= self.radius_mm**2
        if self.kind == "box":
            return np.all(np.abs(p - c) <= 0.5 * np.asarray(self.size_mm), axis=1)
        if self.kind == "ellipsoid":
            return np.sum(((p - c) / np.asarray(self.radii_mm)) ** 2, axis=1) <= 1.0
        if self.kind == "cylinder":
            a = _unit(self.axis)
            d = p - c
            along = d @ a
            radial = d - np.outer(along, a)
            return (np.abs(along) <= 0.5 * self.height_mm) & (
                np.einsum("ij,ij->i", radial, radial) <= self.radius_mm**2
            )
        if self.kind == "surface":
            # the winding number costs points x triangles: only points in the surface's box can be inside
            verts, faces = self.surface_mesh
            box = np.all((p >= verts.min(axis=0)) & (p <= verts.max(axis=0)), axis=1)
            out = np.zeros(len(p), bool)
            out[box] = _inside_closed_surface(p[box], verts, faces)
            return out
        raise ValueError(f"unknown region kind {self.kind!r}")

    def volume_mm3(self, specimen_size_mm=None) -> float:
        """Geometric volume (the background's is the whole box)."""
        if self.kind == "background":
            return float(np.prod(specimen_size_mm))
        if self.kind == "sphere":
            return 4.0 / 3.0 * np.pi * self.radius_mm**3
        if self.kind == "box":
            return float(np.prod(self.size_mm))
        if self.kind == "ellipsoid":
            return 4.0 / 3.0 * np.pi * float(np.prod(self.radii_mm))
        if self.kind == "cylinder":
            return np.pi * self.radius_mm**2 * self.height_mm
        if self.kind == "surface":
            v, f = self.surface_mesh
            a, b, cc = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
            return float(abs(np.einsum("ij,ij->i", a, np.cross(b, cc)).sum()) / 6.0)
        raise ValueError(self.kind)

    def bounds_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box (lo, hi)."""
        c = np.asarray(self.center_mm, float) if self.center_mm is not None else None
        if self.kind == "sphere":
            r = np.full(3, self.radius_mm)
        elif self.kind == "box":
            r = 0.5 * np.asarray(self.size_mm, float)
        elif self.kind == "ellipsoid":
            r = np.asarray(self.radii_mm, float)
        elif self.kind == "cylinder":
            a = _unit(self.axis)
            h = 0.5 * self.height_mm
            r = np.abs(a) * h + self.radius_mm * np.sqrt(np.clip(1.0 - a**2, 0.0, 1.0))
        elif self.kind == "surface":
            v = self.surface_mesh[0]
            return v.min(0), v.max(0)
        else:
            raise ValueError(self.kind)
        return c - r, c + r

    def surface(self, edge_mm: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
        """A closed triangulation (vertices mm, triangles). Curved shapes are scaled
        about their centre so the polygon encloses exactly the analytic volume."""
        v, f = self._polygon(edge_mm)
        if self.kind in ("sphere", "ellipsoid", "cylinder"):
            c = np.asarray(self.center_mm, float)
            a, b, cc = v[f[:, 0]] - c, v[f[:, 1]] - c, v[f[:, 2]] - c
            vol = abs(np.einsum("ij,ij->i", a, np.cross(b, cc)).sum()) / 6.0
            v = c + (v - c) * (self.volume_mm3() / vol) ** (1.0 / 3.0)
        return v, f

    def _polygon(self, edge_mm: float) -> tuple[np.ndarray, np.ndarray]:
        if self.kind == "surface":
            return self.surface_mesh
        if self.kind == "box":
            return box_surface(*self.bounds_mm(), edge_mm)
        # sphere, ellipsoid, cylinder: map a unit sphere / unit cylinder
        c = np.asarray(self.center_mm, float)
        if self.kind in ("sphere", "ellipsoid"):
            radii = np.full(3, self.radius_mm) if self.kind == "sphere" else np.asarray(self.radii_mm, float)
            n = max(3, int(np.ceil(np.pi * radii.max() / edge_mm / 2.0)))
            v, f = _icosphere(n)
            return c + v * radii, f
        if self.kind == "cylinder":
            v, f = _unit_cylinder(self.radius_mm, self.height_mm, edge_mm)
            return c + v @ _frame(_unit(self.axis)).T, f
        raise ValueError(self.kind)


def _unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def _frame(a: np.ndarray) -> np.ndarray:
    """Columns: two unit vectors orthogonal to a, then a."""
    t = np.array([1.0, 0, 0]) if abs(a[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = np.cross(a, t)
    e1 /= np.linalg.norm(e1)
    return np.column_stack([e1, np.cross(a, e1), a])


def _icosphere(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit sphere from a cube whose faces are n x n grids, projected radially."""
    verts, faces = box_surface(np.full(3, -1.0), np.full(3, 1.0), 2.0 / n)
    # equal-angle spacing gives rounder triangles than the plain projection
    verts = np.tan(verts * np.pi / 4.0)
    return verts / np.linalg.norm(verts, axis=1, keepdims=True), faces


def _unit_cylinder(radius: float, height: float, edge: float):
    nt = max(12, int(np.ceil(2 * np.pi * radius / edge)))
    nz = max(2, int(np.ceil(height / edge)) + 1)
    th = np.linspace(0, 2 * np.pi, nt, endpoint=False)
    zs = np.linspace(-height / 2, height / 2, nz)
    side = np.array([[radius * np.cos(t), radius * np.sin(t), z] for z in zs for t in th])
    faces = []
    for k in range(nz - 1):
        for j in range(nt):
            a, b = k * nt + j, k * nt + (j + 1) % nt
            faces += [[a, b, b + nt], [a, b + nt, a + nt]]
    bottom = len(side)
    top = bottom + 1
    verts = np.vstack([side, [[0, 0, -height / 2], [0, 0, height / 2]]])
    for j in range(nt):
        faces.append([bottom, (j + 1) % nt, j])
        faces.append([top, (nz - 1) * nt + j, (nz - 1) * nt + (j + 1) % nt])
    return verts, np.asarray(faces, np.int64)


def box_surface(lo, hi, edge_mm: float, top_lines: tuple[np.ndarray, np.ndarray] | None = None):
    """Closed, outward-oriented triangulation of an axis-aligned box.

    Each face is a structured grid. ``top_lines`` = (x ticks, y ticks) replaces
    the grid of the top face (z = hi) so that lines such as the probe outline are
    edges of the triangulation; the side faces then share those ticks.
    """
    lo = np.asarray(lo, float)
    hi = np.asarray(hi, float)
    ticks = [np.linspace(lo[i], hi[i], max(2, int(np.ceil((hi[i] - lo[i]) / edge_mm)) + 1)) for i in range(3)]
    if top_lines is not None:
        ticks[0], ticks[1] = np.asarray(top_lines[0], float), np.asarray(top_lines[1], float)
    points: dict[tuple, int] = {}
    plist: list = []
    faces: list = []

    def pid(p):
        key = tuple(np.round(p, 9))
        if key not in points:
            points[key] = len(plist)
            plist.append(p)
        return points[key]

    for axis in range(3):
        u, w = [i for i in range(3) if i != axis]
        for side, val in ((0, lo[axis]), (1, hi[axis])):
            tu, tw = ticks[u], ticks[w]
            ids = np.empty((len(tu), len(tw)), int)
            for i, a in enumerate(tu):
                for j, b in enumerate(tw):
                    p = np.empty(3)
                    p[axis], p[u], p[w] = val, a, b
                    ids[i, j] = pid(p)
            # outward normal: +axis on the high side; (u, w, axis) is right-handed for axis 0, 2
            flip = (side == 0) ^ (axis == 1)
            for i in range(len(tu) - 1):
                for j in range(len(tw) - 1):
                    a, b, c, d = ids[i, j], ids[i + 1, j], ids[i + 1, j + 1], ids[i, j + 1]
                    t1, t2 = [a, b, c], [a, c, d]
                    if flip:
                        t1, t2 = t1[::-1], t2[::-1]
                    faces += [t1, t2]
    return np.asarray(plist, float), np.asarray(faces, np.int64)


def _inside_closed_surface(points: np.ndarray, verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Generalised winding number test (robust to small gaps), chunked."""
    inside = np.empty(len(points), bool)
    a0, b0, c0 = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    for s in range(0, len(points), 2048):
        p = points[s : s + 2048, None, :]
        a, b, c = a0[None] - p, b0[None] - p, c0[None] - p
        la, lb, lc = (np.linalg.norm(x, axis=2) for x in (a, b, c))
        det = np.einsum("ijk,ijk->ij", a, np.cross(b, c))
        div = la * lb * lc + np.einsum("ijk,ijk->ij", a, b) * lc + np.einsum("ijk,ijk->ij", b, c) * la + np.einsum("ijk,ijk->ij", c, a) * lb
        w = np.arctan2(det, div).sum(axis=1) / (2 * np.pi)
        inside[s : s + 2048] = np.abs(w) > 0.5
    return inside


def paint_labels(points_mm: np.ndarray, regions: tuple[Region, ...]) -> np.ndarray:
    """Region index of each point: the last region in paint order that contains it."""
    labels = np.zeros(len(points_mm), np.int32)
    for k, r in enumerate(regions):
        if k == 0:
            continue
        labels[r.contains(points_mm)] = k
    return labels
