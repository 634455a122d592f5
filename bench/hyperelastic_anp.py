"""A cheaper discretization for the hyperelastic effect, measured against the P2 solver.

    python bench/hyperelastic_anp.py

The cold hyperelastic solve at paper size (P2, 52,173 unknowns) factorizes its
tangent about 14 times, at about 1.2 s each on a 2-core machine: no setting
brings that to 2 s. This experiment measures the smaller discretization the
notes named, on the demo (moduli 18 and 63 kPa, travels 3.7 to 14.8 mm):

- ANP: linear (4-node) tets with an averaged nodal volume. The neo-Hookean
  energy mu/2 (tr C - 3) - mu ln J is integrated per element, the volumetric
  lam/2 (ln J)^2 on nodal volume ratios J_a = v_a / V_a (v_a a quarter of the
  current volume of each tet around vertex a), which keeps nearly
  incompressible tissue (nu 0.49) from locking as plain linear tets do.
  Newton's method with the exact tangent (its nodal volume term couples each
  vertex with its neighbours' neighbours) and a backtracking line search.
- The corrected field: the P2 linear field plus the ANP's nonlinear part
  (ANP hyperelastic minus ANP linear), whose small-strain limit is the linear
  model's exactly.

Prints, per travel, the probe force of each and, on the demo's warp control
points (the image plane), the corrected field's distance from the P2
hyperelastic one in pixels, beside the nonlinear part itself. The corrected
force came within 1.6% of the P2 solve, but its image-plane field 0.63 px rms
from it at 14.8 mm (of a nonlinear part of 3.7 px): more than the diagnoses'
noise floors (0.1-0.3 px), so not a substitute for the P2 solve the diagnosis
scores (docs/model-check.md, "Speed").
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from app.core.fem import assemble, interpolation_matrix, lame, p1_space  # noqa: E402
from app.core.hyperelastic import neo_hookean_energy, neo_hookean_stress  # noqa: E402
from app.core.solver import Factorized  # noqa: E402

TRAVELS_MM = (3.7, 7.4, 11.1, 14.8)
MODULI_KPA = (18.0, 63.0)
NU = 0.49


class AveragedNodalVolume:
    """Neo-Hookean energy on linear tets with nodal volume ratios (see the module's text)."""

    def __init__(self, fe, youngs_kPa, nu):
        space = fe.space
        self.fe, self.T, self.dN, self.V = fe, space.elems, space.grad_bary, space.volumes_mm3
        self.n, self.m = space.n_nodes, len(self.T)
        mus, lams = np.array([lame(float(E), nu) for E in youngs_kPa]).T
        self.mu = mus[space.labels]
        lam_e = lams[space.labels]
        quarter = np.repeat(self.V / 4, 4)
        self.Va = np.bincount(self.T.ravel(), quarter, minlength=self.n)
        self.lam_a = np.bincount(self.T.ravel(), quarter * np.repeat(lam_e, 4), minlength=self.n) / self.Va
        self.dofs = (3 * self.T[:, :, None] + np.arange(3)).reshape(self.m, 12)
        self.rows = np.repeat(self.dofs, 12, axis=1).ravel()
        self.cols = np.tile(self.dofs, (1, 12)).ravel()
        self.g_rows = np.repeat(self.T, 12, axis=1).ravel()  # nodal volume a of tet e ...
        self.g_cols = np.tile(self.dofs, (1, 4)).ravel()  # ... against the dofs of e

    def _kinematics(self, u):
        F = np.eye(3) + np.einsum("mbi,mbJ->miJ", u.reshape(-1, 3)[self.T], self.dN)
        J = np.linalg.det(F)
        if np.any(J <= 0):
            return None
        Finv = np.linalg.inv(F)
        h = np.einsum("mJi,mbJ->mbi", Finv, self.dN)  # F^-T grad N_b
        Ja = np.bincount(self.T.ravel(), np.repeat(self.V * J / 4, 4), minlength=self.n) / self.Va
        return F, J, Finv, h, Ja

    def energy(self, u) -> float:
        k = self._kinematics(u)
        if k is None or np.any(k[4] <= 0):
            return np.inf
        F, _, _, _, Ja = k
        We = self.V * neo_hookean_energy(F, self.mu, 0.0)  # the law without its volumetric term
        return float(We.sum() + (self.Va * self.lam_a / 2 * np.log(Ja) ** 2).sum())

    def force(self, u, tangent: bool = False):
        F, J, _, h, Ja = self._kinematics(u)
        p_e = (self.lam_a * np.log(Ja) / Ja)[self.T].mean(axis=1)  # nodal pressures, averaged on each tet
        P = neo_hookean_stress(F, self.mu, 0.0)  # mu (F - F^-T)
        fe = self.V[:, None, None] * np.einsum("miJ,mbJ->mbi", P, self.dN) + (p_e * self.V * J)[:, None, None] * h
        f = np.bincount(self.dofs.ravel(), fe.reshape(self.m, 12).ravel(), minlength=3 * self.n)
        if not tangent:
            return f
        Vmu = (self.V * self.mu)[:, None, None, None, None]
        hh = np.einsum("mbi,mck->mbick", h, h)
        K = Vmu * hh.transpose(0, 1, 4, 3, 2) + (p_e * self.V * J)[:, None, None, None, None] * (
            hh - hh.transpose(0, 1, 4, 3, 2))
        S = (self.V * self.mu)[:, None, None] * np.einsum("mbJ,mcJ->mbc", self.dN, self.dN)
        for i in range(3):
            K[:, :, i, :, i] += S
        K_el = sp.csr_matrix((K.ravel(), (self.rows, self.cols)), shape=(3 * self.n,) * 2)
        g = np.repeat(((self.V * J / 4)[:, None, None] * h).reshape(self.m, 1, 12), 4, axis=1).ravel()
        G = sp.csr_matrix((g, (self.g_rows, self.g_cols)), shape=(self.n, 3 * self.n))
        U2 = self.lam_a * (1 - np.log(Ja)) / (Ja ** 2 * self.Va)
        return f, (K_el + G.T @ sp.diags(U2) @ G).tocsr()

    def reaction_N(self, u) -> float:
        return float(-(self.fe.probe_z @ self.force(u)[self.fe.fixed]) * 1e-3)

    def linear(self):
        """The small-strain field per mm of travel (the tangent at rest)."""
        fe = self.fe
        _, K = self.force(np.zeros(3 * self.n), True)
        u = np.zeros(3 * self.n)
        u[fe.fixed] = fe.lift
        f = Factorized(K[fe.free][:, fe.free].tocsc())
        try:
            u[fe.free] = f.solve(-(K[fe.free][:, fe.fixed] @ fe.lift))
        finally:
            f.free()
        return u, float(-(fe.probe_z @ (K @ u)[fe.fixed]) * 1e-3)

    def walk(self, travels, substep_mm: float = 1.0, tol: float = 1e-7):
        """Equilibria at ``travels``: load steps of at most ``substep_mm``, Newton in each."""
        fe, free, fixed = self.fe, self.fe.free, self.fe.fixed
        u, done, fields, n_factor = np.zeros(3 * self.n), 0.0, [], 0
        for d in travels:
            n_sub = max(1, int(np.ceil((d - done) / substep_mm)))
            for s in range(1, n_sub + 1):
                push = fe.lift * (done + (d - done) * s / n_sub) - u[fixed]
                for it in range(40):
                    f, K = self.force(u, True)
                    n_factor += 1
                    rhs = -f[free] - (K[free][:, fixed] @ push if it == 0 else 0.0)
                    fac = Factorized(K[free][:, free].tocsc())
                    try:
                        step = np.zeros_like(u)
                        step[free] = fac.solve(rhs)
                    finally:
                        fac.free()
                    if it == 0:  # the prescribed travel in full, the free part shortened until no tet inverts
                        step[fixed] = push
                        while not np.isfinite(self.energy(u + step)):
                            step[free] *= 0.5
                        u = u + step
                    else:  # backtracking on the energy
                        e0, a = self.energy(u), 1.0
                        while self.energy(u + a * step) > e0 + 1e-12 * abs(e0) and a > 1e-3:
                            a *= 0.5
                        u = u + a * step
                    r = self.force(u)
                    if np.linalg.norm(r[free]) < tol * np.linalg.norm(r[fixed]):
                        break
            done = d
            fields.append(u.copy())
        return np.array(fields), n_factor


def image_plane_px(u3: np.ndarray, problem, exp) -> np.ndarray:
    """Displacements (n, 3) mm at the warp control points -> (n, 2) px on the
    image plane (lateral, axial) of ``problem`` (an identify.Problem)."""
    sc, sr = exp.imaging.pixel_spacing_mm
    return np.column_stack([(u3 @ problem._lat) / sc, u3[:, 2] / sr])


def rms(a: np.ndarray) -> float:
    """RMS length of the rows of ``a`` (n, 2)."""
    return float(np.sqrt((a ** 2).sum(axis=1).mean()))


def main() -> int:
    from app.core.experiment import read_experiment
    from app.core.forward import build_model
    from app.core.hyperelastic import HyperelasticModel
    from app.core.identify import Problem
    from app.core.mesh import specimen_mesh

    exp = read_experiment(ROOT / "resources" / "demo")
    mesh = specimen_mesh(exp)
    travels = np.array(TRAVELS_MM)
    fe2 = build_model(mesh)
    fe1 = build_model(mesh, op=assemble(p1_space(mesh)))
    print(f"demo mesh: {mesh.n_nodes} vertices, {mesh.n_tets} tets; P2 {len(fe2.free)} free dofs, "
          f"ANP {len(fe1.free)}")
    u2_lin, k2 = fe2.solve(list(MODULI_KPA), NU)
    t = time.perf_counter()
    hm = HyperelasticModel(fe2, warm_starts=False)
    p2 = hm.solve(list(MODULI_KPA), NU, travels)
    hm.free()
    t_p2 = time.perf_counter() - t
    anp = AveragedNodalVolume(fe1, MODULI_KPA, NU)
    u1_lin, k1 = anp.linear()
    t = time.perf_counter()
    fields1, n_factor = anp.walk(travels)
    t_anp = time.perf_counter() - t
    print(f"P2 hyperelastic walk {t_p2:.1f} s; ANP walk {t_anp:.1f} s ({n_factor} factorizations, plain Newton)")
    print(f"linear force per mm of travel: P2 {k2:.4f} N, ANP {k1:.4f} N")
    pr = Problem.from_experiment(exp, mesh=mesh)
    pts = pr.ctrl_world
    I2, I1 = interpolation_matrix(fe2.space, pts), interpolation_matrix(fe1.space, pts)

    def px(u3):
        return image_plane_px(u3, pr, exp)

    print(f"{'travel mm':>9s} {'F P2 hyper':>10s} {'F P2 lin':>8s} {'F corr':>7s} {'F ANP':>6s} "
          f"{'nonlinear px':>12s} {'corr - P2 px':>12s} {'max px':>6s}")
    for k, d in enumerate(travels):
        hyper = (I2 @ p2.fields[k]).reshape(-1, 3)
        lin = d * (I2 @ u2_lin).reshape(-1, 3)
        corr = lin + (I1 @ (fields1[k] - d * u1_lin)).reshape(-1, 3)
        f_anp = anp.reaction_N(fields1[k])
        print(f"{d:9.1f} {p2.force_N[k]:10.3f} {d * k2:8.3f} {d * k2 + f_anp - d * k1:7.3f} {f_anp:6.2f} "
              f"{rms(px(hyper - lin)):12.2f} {rms(px(corr - hyper)):12.2f} {np.abs(px(corr - hyper)).max():6.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
