"""Small meshes and experiments shared by the core tests."""

from __future__ import annotations

import numpy as np

from app.core.mesh import TetMesh


def cube_mesh(n: int, size=(1.0, 1.0, 1.0), probe_rect=None, labels=None) -> TetMesh:
    """Structured tet mesh of a box: n^3 cubes, six tets each (Kuhn subdivision)."""
    sx, sy, sz = size
    xs, ys, zs = np.linspace(0, sx, n + 1), np.linspace(0, sy, n + 1), np.linspace(0, sz, n + 1)
    X, Y, Z = np.meshgrid(xs, ys, zs, indexing="ij")
    pts = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    idx = np.arange(len(pts)).reshape(n + 1, n + 1, n + 1)
    c = np.stack([idx[:-1, :-1, :-1], idx[1:, :-1, :-1], idx[1:, 1:, :-1], idx[:-1, 1:, :-1],
                  idx[:-1, :-1, 1:], idx[1:, :-1, 1:], idx[1:, 1:, 1:], idx[:-1, 1:, 1:]], -1).reshape(-1, 8)
    kuhn = [(0, 1, 2, 6), (0, 2, 3, 6), (0, 3, 7, 6), (0, 7, 4, 6), (0, 4, 5, 6), (0, 5, 1, 6)]
    tets = np.concatenate([c[:, list(k)] for k in kuhn])
    p = pts[tets]
    vol = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])
    neg = vol < 0
    tets[neg, 1], tets[neg, 2] = tets[neg, 2].copy(), tets[neg, 1].copy()
    lab = np.zeros(len(tets), np.int32) if labels is None else labels(pts[tets].mean(axis=1))
    names = tuple(f"R{i}" for i in range(int(lab.max()) + 1))
    return TetMesh(pts, tets, lab, names, (sx, sy, sz), probe_rect or (0.0, sx, 0.0, sy))
