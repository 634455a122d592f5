"""The neo-Hookean solver against a closed form, a finite-difference tangent and
the linear model at small strain."""

import re

import numpy as np
import pytest

from app.core.fem import coefficients
from app.core.forward import Boundary, build_model
from app.core.hyperelastic import HyperelasticModel, neo_hookean_energy, neo_hookean_stress, uniaxial_stress_kPa
from tests.core.helpers import cube_mesh


def test_stress_is_the_derivative_of_the_energy():
    rng = np.random.default_rng(0)
    F = np.eye(3) + 0.2 * rng.standard_normal((5, 3, 3))
    mu, lam = 3.0, 40.0
    P = neo_hookean_stress(F, mu, lam)
    h = 1e-6
    for i in range(3):
        for j in range(3):
            dF = np.zeros((3, 3))
            dF[i, j] = h
            fd = (neo_hookean_energy(F + dF, mu, lam) - neo_hookean_energy(F - dF, mu, lam)) / (2 * h)
            assert np.allclose(P[:, i, j], fd, rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize("nu", [0.3, 0.45])
def test_uniaxial_compression_matches_the_closed_form(nu):
    """A cube pressed on its whole top face with frictionless faces deforms
    homogeneously: F = diag(a, a, s). The FE reaction equals the closed form's
    nominal stress (lateral stretch a from a scalar root find) times the area."""
    mesh = cube_mesh(2, size=(10.0, 10.0, 10.0), probe_rect=(0.0, 10.0, 0.0, 10.0))
    fe = build_model(mesh, Boundary("sliding", "slip"))
    hm = HyperelasticModel(fe, tol=1e-10)
    E = 20.0
    depths = np.array([0.5, 1.0, 2.0, 3.0])
    sol = hm.solve([E], nu, depths)
    for d, F in zip(depths, sol.force_N):
        P33, a = uniaxial_stress_kPa(1.0 - d / 10.0, E, nu)
        assert F == pytest.approx(-P33 * 100.0 * 1e-3, rel=1e-6)
    # and it is not the linear answer: neo-Hookean compression stiffens
    _, g = fe.solve([E], nu)
    assert sol.force_N[-1] > 1.02 * g * depths[-1]
    hm.free()


def test_tangent_matches_finite_differences_and_small_strain_is_linear():
    mesh = cube_mesh(2, size=(10.0, 10.0, 8.0), probe_rect=(2.5, 7.5, 2.5, 7.5),
                     labels=lambda c: (c[:, 2] > 4).astype(np.int32))
    fe = build_model(mesh)
    hm = HyperelasticModel(fe)
    E, nu = [10.0, 25.0], 0.45
    mu, lam = hm.element_moduli(E, nu)
    u_lin, g = fe.solve(E, nu)
    # at u = 0 the tangent is the linear stiffness exactly
    T0 = hm._upper_matrix(hm.tangent_upper(np.zeros(fe.space.n_dofs), mu, lam))
    A, _, _, _ = fe.term_blocks(coefficients(E, nu))
    import scipy.sparse as sp

    assert abs(T0 - sp.triu(A)).max() <= 1e-12 * abs(A).max()
    # at a deformed state: directional derivative of the internal force
    u = 0.8 * u_lin
    v = np.zeros_like(u)
    v[fe.free] = np.random.default_rng(1).standard_normal(len(fe.free)) * 1e-2
    eps = 1e-5
    fd = (hm.internal_force(u + eps * v, mu, lam) - hm.internal_force(u - eps * v, mu, lam)) / (2 * eps)
    T = hm._upper_matrix(hm.tangent_upper(u, mu, lam))
    T = T + sp.triu(T, 1).T
    assert np.linalg.norm(T @ v[fe.free] - fd[fe.free]) < 1e-6 * np.linalg.norm(fd[fe.free])
    # a tiny indentation gives the linear force per mm
    sol = hm.solve(E, nu, [1e-4])
    assert sol.force_N[0] / 1e-4 == pytest.approx(g, rel=1e-3)
    hm.free()


def test_a_warm_solve_reuses_the_kept_equilibria_and_agrees_with_a_cold_one():
    """Inside a fit, a solve with nearby moduli starts each travel from the
    equilibrium the last solve left there: no factorization, and the same answer
    (to the solver's tolerance) as a fresh model walking the load path."""
    mesh = cube_mesh(3, size=(10.0, 10.0, 8.0), probe_rect=(2.5, 7.5, 2.5, 7.5),
                     labels=lambda c: (c[:, 2] > 4).astype(np.int32))
    fe = build_model(mesh)
    depths = [0.6, 1.2]
    warm = HyperelasticModel(fe)
    warm.solve([10.0, 25.0], 0.45, depths)
    n_fact = warm.n_factorizations
    E = [10.5, 24.0]
    s_warm = warm.solve(E, 0.45, depths)
    assert warm.n_factorizations == n_fact  # the kept tangents served
    cold = HyperelasticModel(fe)
    s_cold = cold.solve(E, 0.45, depths)
    assert s_warm.force_N == pytest.approx(s_cold.force_N, rel=1e-5)
    assert np.abs(s_warm.fields - s_cold.fields).max() < 1e-5 * np.abs(s_cold.fields).max()
    warm.free()
    cold.free()


def _live_factors(hm: HyperelasticModel) -> int:
    held = [p.factor for p in hm._held()]
    return len({id(f) for f in held if f._handle is not None or f._fallback is not None})


def test_short_of_memory_the_travels_keep_equilibria_without_factors_and_the_answers_do_not_change(monkeypatch):
    """With no memory to spare (ELASTOID_MEMORY_GB below what the process holds)
    no requested travel keeps a factor of its own: the linear one, the walk's and
    the spare are all that live, where plenty of memory keeps one per travel too.
    The equilibria are the same, and a warm solve from the kept equilibria
    (iterating with a neighbour's factor) agrees with a cold one."""
    mesh = cube_mesh(3, size=(10.0, 10.0, 8.0), probe_rect=(2.5, 7.5, 2.5, 7.5),
                     labels=lambda c: (c[:, 2] > 4).astype(np.int32))
    fe = build_model(mesh)
    depths = [0.4, 0.8, 1.2]
    roomy = HyperelasticModel(fe)
    s_roomy = roomy.solve([10.0, 25.0], 0.45, depths)
    assert roomy.n_lean == 0 and all(d in roomy._cache for d in depths)

    monkeypatch.setenv("ELASTOID_MEMORY_GB", "0.001")
    lean = HyperelasticModel(fe)
    s_lean = lean.solve([10.0, 25.0], 0.45, depths)
    assert lean.n_lean == len(depths)
    assert not any(d in lean._cache for d in depths), sorted(lean._cache)
    assert _live_factors(lean) <= 3 < _live_factors(roomy)
    assert s_lean.force_N == pytest.approx(s_roomy.force_N, rel=1e-5)
    assert np.abs(s_lean.fields - s_roomy.fields).max() < 1e-5 * np.abs(s_roomy.fields).max()

    E = [10.5, 24.0]
    trace_from = len(lean.trace)
    s_warm = lean.solve(E, 0.45, depths)
    # each travel started from its kept equilibrium (one load step each), not from the walk
    stepped = sorted({d for d, *_ in lean.trace[trace_from:]})
    assert stepped == depths, stepped
    cold = HyperelasticModel(fe)
    monkeypatch.delenv("ELASTOID_MEMORY_GB")
    s_cold = cold.solve(E, 0.45, depths)
    assert s_warm.force_N == pytest.approx(s_cold.force_N, rel=1e-5)
    assert np.abs(s_warm.fields - s_cold.fields).max() < 1e-5 * np.abs(s_cold.fields).max()
    for hm in (roomy, lean, cold):
        hm.free()


def test_a_load_path_the_solver_cannot_follow_stops_with_a_clear_message():
    """Pressed to 90% of its height under a bonded probe, the elements beside the
    probe's edges invert: the solve gives up with the travel it reached instead
    of bisecting forever. (Before its iteration kept indefinite tangents out, it
    stalled at 4.x mm, and on the demo phantom at 12.5 of 14.8 mm. Pressed to
    80%, 6.4 mm, it gave up at 5.76 mm while its tangents were LDL^T factors;
    with Cholesky factors its walk took other steps and reached 6.4 mm, a stable
    equilibrium: det F >= 0.24, tangent positive definite.)
    How far it gets depends on the steps the walk happens to take, and those on
    the last bits of the factorizations: 5.6 mm on the Intel machines this was
    written on, 6.88 mm on an AMD EPYC (MKL takes other code paths there). So
    the test asks for a clear stop beyond 5 mm (the stall of the defect above
    was at 4.x mm; the next test reaches 5.6 mm, 70%) and short of the 7.2 mm
    asked, not for one figure."""
    from app.core.errors import ElastoidError

    mesh = cube_mesh(4, size=(10.0, 10.0, 8.0), probe_rect=(2.5, 7.5, 2.5, 7.5))
    hm = HyperelasticModel(build_model(mesh), max_iterations=20)
    with pytest.raises(ElastoidError, match=r"cannot follow the load path beyond \d+\.\d+ mm of probe travel") as err:
        hm.solve([10.0], 0.45, [7.2])
    hm.free()
    reached = float(re.search(r"beyond (\d+\.\d+) mm", str(err.value)).group(1))
    assert 5.0 <= reached < 7.2


def test_the_equilibrium_does_not_depend_on_the_requested_travels_on_the_way():
    """Pressed to 70% of its height, with or without stops at 2 and 4 mm: the same
    equilibrium. With stops, the walk meets iterates near 4.6 mm whose tangent is
    indefinite; iterating with such a tangent stalled there (steps of 0.0025 mm
    failed) until indefinite tangents were shifted towards their diagonal."""
    mesh = cube_mesh(4, size=(10.0, 10.0, 8.0), probe_rect=(2.5, 7.5, 2.5, 7.5))
    fe = build_model(mesh)
    direct = HyperelasticModel(fe, max_iterations=20).solve([10.0], 0.45, [5.6])
    hm = HyperelasticModel(fe, max_iterations=20)
    stops = hm.solve([10.0], 0.45, [2.0, 4.0, 5.6])
    assert stops.force_N[-1] == pytest.approx(direct.force_N[-1], rel=1e-4)
    assert np.abs(stops.fields[-1] - direct.fields[-1]).max() < 1e-3
    mu, lam = hm.element_moduli([10.0], 0.45)
    f = hm.internal_force(stops.fields[-1], mu, lam)
    assert np.linalg.norm(f[fe.free]) < 1e-5 * np.linalg.norm(f[fe.fixed])
    hm.free()


def test_elements_beside_the_probe_outline_get_a_richer_rule_with_the_same_linear_limit():
    """Beside the probe's outline the solver integrates with eight points (exact for
    cubics) instead of four; both integrate the small-strain stiffness exactly, so
    the tangent at rest is still the linear model's stiffness."""
    from math import factorial

    from app.core.hyperelastic import EDGE_BARY, EDGE_W

    # exact for every monomial of degree <= 3 on the unit tet: int x^a y^b z^c = a! b! c! / (a+b+c+3)!
    x, y, z = EDGE_BARY[:, 1], EDGE_BARY[:, 2], EDGE_BARY[:, 3]
    assert np.all(EDGE_W > 0)
    for a in range(4):
        for b in range(4 - a):
            for c in range(4 - a - b):
                exact = factorial(a) * factorial(b) * factorial(c) / factorial(a + b + c + 3)
                assert np.sum(EDGE_W * x**a * y**b * z**c) / 6.0 == pytest.approx(exact, rel=1e-12)
    mesh = cube_mesh(4, size=(10.0, 10.0, 8.0), probe_rect=(2.5, 7.5, 2.5, 7.5),
                     labels=lambda c: (c[:, 2] > 4).astype(np.int32))
    fe = build_model(mesh)
    hm = HyperelasticModel(fe)
    # the tets touching the outline's 16 top vertices, and one ring of neighbours
    P = mesh.points_mm[mesh.tets].mean(axis=1)
    assert 0 < len(hm.edge) < mesh.n_tets
    assert np.all(P[hm.edge, 2] > 8.0 - 2 * 2.5)
    E, nu = [10.0, 25.0], 0.45
    mu, lam = hm.element_moduli(E, nu)
    T0 = hm._upper_matrix(hm.tangent_upper(np.zeros(fe.space.n_dofs), mu, lam))
    A, _, _, _ = fe.term_blocks(coefficients(E, nu))
    import scipy.sparse as sp

    assert abs(T0 - sp.triu(A)).max() <= 1e-12 * abs(A).max()
    # and the four-point model (edge_rule=False) has the same tangent at rest
    four = HyperelasticModel(fe, edge_rule=False)
    assert len(four.edge) == 0
    T4 = four._upper_matrix(four.tangent_upper(np.zeros(fe.space.n_dofs), mu, lam))
    assert abs(T0 - T4).max() <= 1e-12 * abs(A).max()


def test_many_frames_ask_for_a_bounded_number_of_travels_and_the_rest_are_interpolated():
    """spread_marks(): with a frame every half millimetre the hyperelastic solve was
    asked for every frame's travel (30 at paper size; one kept factor each, and the
    diagnosis peaked at 10.1 GB during it). At most MAX_LOAD_STEPS travels are
    asked for now, spread evenly and always reaching the deepest; fewer are kept
    as they are. The correction at a travel between them is quadratic through the
    three nearest steps and the rest state: exact for a correction growing as d^2
    (and for one linear in d), which a linear interpolation is not."""
    from types import SimpleNamespace

    from app.core.effects.model import MAX_LOAD_STEPS, EffectProblem, spread_marks

    assert spread_marks([2.5, 5.0], MAX_LOAD_STEPS) == [2.5, 5.0]
    marks = list(np.round(np.linspace(14.8 / 30, 14.8, 30), 3))
    kept = spread_marks(marks, MAX_LOAD_STEPS)
    assert len(kept) == MAX_LOAD_STEPS and kept[-1] == 14.8 and set(kept) <= set(marks)
    assert np.diff(kept).max() < 2 * 14.8 / MAX_LOAD_STEPS and kept == sorted(kept)

    depths = np.array(kept)
    for law in (lambda d: d**2, lambda d: 3.0 * d, lambda d: 0.2 * d**2 - d):
        C = np.stack([law(d) * np.array([[1.0, -2.0, 0.5]]) for d in depths])  # (steps, points, xyz)
        fake = SimpleNamespace(_hyper=SimpleNamespace(depths_mm=depths, corrections={"p": C}))
        for d in (*marks, 0.2, 15.3):  # every frame, before the first step, beyond the last
            got = EffectProblem._correction_at(fake, "p", d)
            np.testing.assert_allclose(got, law(d) * np.array([[1.0, -2.0, 0.5]]), atol=1e-9 * (1 + abs(law(d))))
