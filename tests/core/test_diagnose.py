"""Diagnosis on synthetic experiments with a hidden effect (made by the simulator
on a finer mesh than identification uses), on data without one, and the
version history.

Meshes are coarse on purpose (a few thousand vertices) to keep the suite short,
and the candidate lists leave out hyperelastic (it refits a neo-Hookean model)
except in its own hidden-effect test.

The experiments and meshes are fixed. The experiments (tests/data/experiments/
diagnose, the cases of synthetic.DIAGNOSE_CASES) were written by the simulator
with ``python -m tests.core.synthetic``: simulating them took about 3 minutes of
the suite (the neo-Hookean truth 80 s). fTetWild is not deterministic, and on
fresh meshes the outcome of a case varies from run to run (the spread over fresh
meshes is measured by bench/diagnose_effects.py and reported in
docs/model-check.md). The identification mesh and the truth meshes are in
tests/data/meshes, named by their cache key, and copied into the mesh cache by
tests/conftest.py, so a run is reproducible. After a change to meshing
(MESH_VERSION) the keys change: the fixture says so; regenerate the meshes by
running this file with an empty cache and copying the new files from the cache,
then write the experiments again.
"""

import json
import math
import threading
import weakref
from pathlib import Path

import numpy as np
import pytest

from app.core.diagnose import ModelCheck, ModelHistory, diagnose
from app.core.errors import Cancelled, ElastoidError
from app.core.experiment import read_experiment
from app.core.simulate import read_truth
from tests.core import synthetic

ROOT = Path(__file__).resolve().parents[2]

ID_MESH = synthetic.DIAGNOSE_ID_MESH
BASE = synthetic.DIAGNOSE_BASE
FAST = synthetic.DIAGNOSE_FAST
_make = synthetic.diagnose_experiment
_moduli_errors = synthetic.moduli_errors


@pytest.fixture(scope="module")
def visco(tmp_path_factory):
    exp = _make(tmp_path_factory, "visco")
    return exp, diagnose(exp, candidates=FAST, mesh_settings=ID_MESH)


def _assert_viscoelasticity_named(exp, d):
    """The verdict is viscoelastic; with it the force misfit falls 3x, g1 is
    within 15% of the truth's 0.35 and the moduli within 10%."""
    assert d.verdict == "viscoelastic", d.lines()
    c = d.candidate("viscoelastic")
    assert c.material and c.signature >= 0.6, d.lines()
    assert d.baseline.misfit["force_rms_N"] / c.misfit["force_rms_N"] >= 3.0, d.lines()
    assert c.parameters["g1"] == pytest.approx(0.35, rel=0.15)
    for region, err in _moduli_errors(c.parameters, read_truth(exp.path)["moduli_kPa"]).items():
        assert abs(err) < 0.10, (region, err, d.lines())
    return c


def test_hidden_viscoelasticity_is_named_and_adding_it_fixes_the_model(visco):
    exp, d = visco
    c = _assert_viscoelasticity_named(exp, d)
    assert d.rank_of("viscoelastic") == 1
    assert "relaxes" in c.evidence and "constant" in c.evidence
    payload = d.to_json_dict()
    assert payload["verdict"] == "viscoelastic" and payload["candidates"][0]["effect"] == "viscoelastic"
    assert {"total", "nmi", "force_rms_N"} <= set(payload["candidates"][0]["cost"])
    # the model called for, identified as identify does (NMI and force) from the candidate's
    # maximum-likelihood fit: its cost is no higher there, and its moduli are the ones reported
    ident = payload["identified"]
    assert ident["effects"] == ["viscoelastic"] and set(ident["parameters"]) == set(c.parameters)
    assert ident["cost"]["total"] <= c.cost["total"]
    for region, err in _moduli_errors(ident["parameters"], read_truth(exp.path)["moduli_kPa"]).items():
        assert abs(err) < 0.10, (region, err, d.lines())
    assert any(line.startswith("identified (viscoelastic; NMI and force") for line in d.lines()), d.lines()
    # the current model was identified by the diagnosis too: that is its identification
    assert d.baseline.identified is not None and d.baseline.identified["parameters"] != d.baseline.parameters


def test_hidden_viscoelasticity_on_the_second_geometry(tmp_path_factory):
    """The soft ellipsoid phantom (seed 21). Measured 2026-11-26 on the committed
    meshes: named first (score 60,981, pattern match 99%, "the force relaxes by
    14%"), g1 0.349 and tau 2.01 s (truth 0.35, 2 s), moduli -1.4% and -8.2%
    (baseline -29% and -34%), force misfit 0.149 -> 0.020 N RMS."""
    exp = _make(tmp_path_factory, "e-visco")
    _assert_viscoelasticity_named(exp, diagnose(exp, candidates=FAST, mesh_settings=ID_MESH))


def test_the_inclusions_reference_is_the_current_model_on_the_inclusions_mesh(monkeypatch):
    """same_mesh_model(): the inclusion candidate's own tets and points, its sphere's
    tets given back to the described regions they lie in (here both B and A: the
    located sphere overlaps A), every other tet's label kept."""
    from dataclasses import replace
    from types import SimpleNamespace

    from app.core import diagnose as dg
    from app.core.geometry import Region, paint_labels
    from app.core.mesh import specimen_mesh

    exp = read_experiment(synthetic.diagnose_case("inclusion"))
    located = Region("I", "sphere", center_mm=(24.7, 20.0, 13.8), radius_mm=4.5)  # where the scan puts it
    mesh = specimen_mesh(replace(exp, specimen=exp.specimen.with_region(located)), ID_MESH)  # committed
    assert mesh.region_names == ("B", "A", "I")
    seen = {}
    monkeypatch.setattr(dg.EffectProblem, "from_experiment",
                        classmethod(lambda cls, e, **kw: seen.update(exp=e, **kw)))
    current = SimpleNamespace(exp=exp, mesh=SimpleNamespace(region_names=("B", "A")), effects=(), frames=(0, 1, 2),
                              roi=None, nu=0.49, cost_kind="joint", inclusion=None)
    dg.same_mesh_model(current, SimpleNamespace(mesh=mesh, rm=None), near_kPa=[15.0, 45.0])
    m = seen["mesh"]
    assert seen["exp"] is exp and seen["near_kPa"] == [15.0, 45.0]
    assert m.region_names == ("B", "A") and m.points_mm is mesh.points_mm and m.tets is mesh.tets
    sphere = mesh.labels == 2
    assert np.array_equal(m.labels[~sphere], mesh.labels[~sphere])
    centroids = mesh.points_mm[mesh.tets[sphere]].mean(axis=1)
    assert np.array_equal(m.labels[sphere], paint_labels(centroids, exp.specimen.regions))
    assert set(np.unique(m.labels[sphere])) == {0, 1}
    assert mesh.labels.max() == 2  # the candidate's own mesh is left as it was


def test_model_check_adds_the_verdict_as_a_version_and_reverts(visco):
    exp, _ = visco
    mc = ModelCheck(exp, mesh_settings=ID_MESH)
    v0 = mc.identify(())
    cmp0 = mc.compare()
    assert len(cmp0.force_model_N) == len(exp.force_log.force_N)
    assert set(cmp0.region_share) == {"B", "A"} and sum(cmp0.region_share.values()) == pytest.approx(1.0)
    assert cmp0.frames[0].residual_map.shape == cmp0.frames[0].target_roi.shape
    d = mc.diagnose(candidates=("viscoelastic", "probe-slip"))
    assert d.verdict == "viscoelastic"
    # each candidate keeps its model for an add but frees what it does not share with the current one
    assert d.candidate("viscoelastic").problem.rm is mc.problem.rm and mc.problem.rm._prec is not None
    assert d.candidate("probe-slip").problem.rm._prec is None
    v1 = mc.add()
    assert v1.effects == ("viscoelastic",) and v1.parent == 0
    # the version holds the verdict's identification (NMI and force, as the first version's), not
    # the maximum-likelihood fit the candidate was scored with
    assert d.identified["effects"] == ["viscoelastic"] and d.baseline.identified is None  # version 0 given
    assert v1.parameters == d.identified["parameters"] != d.candidate("viscoelastic").parameters
    assert v1.cost == d.identified["cost"]
    errs = mc.history.errors()
    assert errs["label"] == ["baseline", "+ viscoelastic"]
    assert errs["force_rms_N"][1] < errs["force_rms_N"][0] / 3
    assert mc.history.compare(0, 1)["added"] == ["viscoelastic"]
    assert v1.warning == ""  # the verdict is supported
    mc.revert(0)
    assert mc.effects == () and len(mc.history) == 2
    # an effect the diagnosis did not support can be added, and its version says so
    assert d.candidate("probe-slip").score < 0
    # a new diagnosis first frees the last one's candidate models that no version uses; cancelled
    # here, it leaves the last diagnosis as it was, and probe-slip's model is rebuilt when added
    slip = weakref.ref(d.candidate("probe-slip").problem)
    stop = threading.Event()
    stop.set()
    with pytest.raises(Cancelled):
        mc.diagnose(candidates=("probe-slip",), cancel=stop)
    assert mc.last_diagnosis is d and slip() is None
    assert d.candidate("probe-slip").problem is None and d.candidate("probe-slip").fitted
    assert d.candidate("viscoelastic").problem is mc._problems[1]  # version 1's model stays
    v2 = mc.add("probe-slip")
    assert v2.parent == 0 and v2.warning and "revert to version 0" in v2.warning
    assert mc.history.versions[2].warning == v2.warning
    assert ModelHistory.from_json_dict(mc.history.to_json_dict()) == mc.history
    mc.revert(1)
    with pytest.raises(ElastoidError, match="diagnose the current version"):
        mc.add("viscoelastic")  # the diagnosis was made for version 0
    # identified with effects of the user's choice: warned when it fits worse than its parent
    mc.revert(0)
    v3 = mc.identify(("probe-slip",))
    assert v3.parent == 0 and "worse than version 0" in v3.warning, v3.misfit
    mc.revert(0)
    assert mc.identify(("viscoelastic",)).warning == ""

    # saved (a session file) and restored: the same versions, live again
    import json

    again = ModelCheck.restored(exp, json.loads(json.dumps(mc.state())), mesh_settings=ID_MESH)
    assert again.history == mc.history and again.effects == ("viscoelastic",)
    assert np.allclose(again.tracked.noise_px, mc.tracked.noise_px)  # the speckle tracked as the first time
    for i in (again.history.current, 1, 2):  # the current version's model, then others rebuilt when asked
        new, old = again.compare(i), mc.compare(i)
        assert np.allclose(new.force_model_N, old.force_model_N, rtol=1e-6, atol=1e-9), i
        assert np.allclose(new.frames[-1].model_px, old.frames[-1].model_px, atol=1e-6), i
    # the last diagnosis (of version 0) is read back as it was, and its verdict added from
    # it without diagnosing again: the candidate's model rebuilt at its fitted parameters
    rd = again.last_diagnosis
    assert again.diagnosed_version == 0 and rd.lines() == d.lines() and rd.to_json_dict() == d.to_json_dict()
    assert rd.candidate("viscoelastic").problem is None and rd.candidate("viscoelastic").fitted
    with pytest.raises(ElastoidError, match="diagnose the current version"):
        again.add()  # made for version 0
    again.revert(0)
    v_re = again.add()
    assert (v_re.effects, v_re.parameters, v_re.warning) == (v1.effects, v1.parameters, "") and v_re.parent == 0
    for k, x in v1.misfit.items():
        assert v_re.misfit[k] == pytest.approx(x, rel=1e-6, abs=1e-9), k
    assert again.revert(2).effects == ("probe-slip",) and again.effects == ("probe-slip",)
    d = again.diagnose(candidates=("viscoelastic",))
    assert d.baseline.effects == ("probe-slip",) and again.state()["diagnosis"]["version"] == 2
    assert again.add("viscoelastic").parent == 2 and len(again.history) == len(mc.history) + 2
    assert ModelCheck(exp).state() == {"history": {"current": -1, "versions": []}}  # no diagnosis, none saved


def test_a_candidate_of_a_hyperelastic_model_refreshes_warm_and_release_keeps_what_is_shared(tmp_path_factory):
    """When the current model has the hyperelastic effect, a candidate on the same
    FE model (here viscoelastic) refreshes from the equilibria the current model's
    solver kept: no factorization, the same force to the solver's tolerance.
    Released once scored, it leaves that shared solver and reduced model alone.
    A candidate on another FE model (sliding-bottom) does not share it. A model
    released on its own frees both and still evaluates as before."""
    from app.core.diagnose import current_model
    from app.core.effects.model import EffectProblem

    exp = _make(tmp_path_factory, "hyper")
    current = current_model(exp, ("hyperelastic",), mesh_settings=ID_MESH)
    params = current.complete({f"E_{k}_kPa": v for k, v in read_truth(exp.path)["moduli_kPa"].items()})
    current.refresh_hyperelastic(params)
    solver = current._hyper_model
    n = solver.n_factorizations
    kw = dict(base=current, frames=current.frames, nu=current.nu)
    visco = EffectProblem.from_experiment(exp, effects=("viscoelastic", "hyperelastic"), **kw)
    visco.share_hyperelastic_solver(current)
    visco.refresh_hyperelastic(params)
    assert visco._hyper_model is solver and solver.n_factorizations == n
    assert visco._hyper.force_N == pytest.approx(current._hyper.force_N, rel=1e-5)
    visco.release(keep=current)
    assert current._hyper_model is solver and solver._cache and current.rm._prec is not None
    slide = EffectProblem.from_experiment(exp, effects=("sliding-bottom", "hyperelastic"), **kw)
    slide.share_hyperelastic_solver(current)  # another boundary partition: not shared
    assert slide._hyper_model is None
    before = current.evaluate(params)["total"]
    current.release()
    assert current._hyper_model is None and current.rm._prec is None
    assert current.evaluate(params)["total"] == before  # released, it evaluates as before


def test_identifying_with_the_hyperelastic_effect_starts_it_at_the_linear_models_optimum(tmp_path_factory,
                                                                                           monkeypatch):
    """A round of the large-deformation fit moves the moduli's ratios by at most
    WARM_REACH (so that its refresh is a warm solve), and from equal moduli its
    three rounds could not pass 1.45^3 = 3.05: on a neo-Hookean paper phantom
    (ratio 3.5, blind seed 27107) ``identify --effects hyperelastic`` stopped at
    3.05, E_A -12%, in 271 s. Each start is now fitted with the linear model
    first, and the large-deformation fit starts at that optimum: the same seed
    gave E_A -0.7% in 125 s (docs/model-check.md, "The moduli an added effect
    gives"). Here the large-deformation fit and its refresh are stubbed; what is
    checked is where it starts, and that the linear fit saw no correction."""
    import app.core.effects.model as em
    from app.core.diagnose import current_model

    exp = _make(tmp_path_factory, "hyper")
    problem = current_model(exp, ("hyperelastic",), mesh_settings=ID_MESH)
    started, linear_seen = [], []
    real_fit = em.fit

    linear_ends = []

    def fit(problem, start, **kw):
        linear_seen.append(problem._hyper is None)
        out = real_fit(problem, start, **kw)
        linear_ends.append(out.parameters)
        return out

    def fit_hyperelastic(problem, start, **kw):
        started.append(problem.moduli(start))
        return real_fit(problem, start, **{**kw, "max_evaluations": 1})

    monkeypatch.setattr(em, "fit", fit)
    monkeypatch.setattr(em, "fit_hyperelastic", fit_hyperelastic)
    monkeypatch.setattr(problem, "refresh_hyperelastic", lambda *a, **k: None)
    res = em.identify_with_effects(problem, (10.0, 30.0))
    assert linear_seen and all(linear_seen) and len(linear_ends) == 2
    ratios = [E[1] / E[0] for E in started]  # A over B; the truth's is 3
    assert all(r > em.WARM_REACH ** 3 for r in ratios), ratios  # out of reach of three rounds from 1
    assert res.parameters["E_A_kPa"] / res.parameters["E_B_kPa"] == pytest.approx(ratios[0], rel=0.02)
    # a start whose linear fit ends where an earlier one's did shares its large-deformation fit
    same = all(abs(linear_ends[1][k] / v - 1) <= em.SAME_OPTIMUM_RTOL for k, v in linear_ends[0].items())
    assert len(started) == (1 if same else 2) and len(res.starts) == 2
    if same:
        assert res.starts[1]["parameters"] == res.starts[0]["parameters"] and "earlier start" in res.starts[1]["note"]
    else:
        assert ratios[0] == pytest.approx(ratios[1], rel=0.02)  # both starts' linear fits agree
    # the rule itself: within SAME_OPTIMUM_RTOL in every parameter, and only then
    a = {"E_B_kPa": 18.0, "E_A_kPa": 63.0}
    assert em._same_optimum(a, {"E_B_kPa": 18.1, "E_A_kPa": 62.5})
    assert not em._same_optimum(a, {"E_B_kPa": 18.0, "E_A_kPa": 64.0})


def test_the_hyperelastic_correction_is_exact_along_the_moduli_level_and_the_fit_ends_with_it(tmp_path_factory):
    """Pressed by a prescribed travel, a neo-Hookean body (Poisson's ratio fixed)
    takes the same displacements at every level of its moduli and its force scales
    with them: the correction computed at one level is the one solved at another.
    fit_hyperelastic ends with a fit of the level alone (_fit_level), which needs
    no refresh: on the linear demo its round was refused and it had kept the force
    misfit of the neo-Hookean stiffening, 0.28 N for a noise of 0.02 N (now 0.07 N)."""
    import app.core.effects.model as em
    from app.core.diagnose import current_model

    exp = _make(tmp_path_factory, "hyper")
    problem = current_model(exp, ("hyperelastic",), mesh_settings=ID_MESH)
    p = {"E_B_kPa": 18.0, "E_A_kPa": 54.0}
    up = {k: 1.25 * v for k, v in p.items()}
    problem.refresh_hyperelastic(p)
    frozen = problem.evaluate(up)
    problem.refresh_hyperelastic(up)
    solved = problem.evaluate(up)
    assert frozen["nmi"] == pytest.approx(solved["nmi"], abs=1e-6)
    assert frozen["force_rms_N"] == pytest.approx(solved["force_rms_N"], rel=1e-4, abs=1e-6)
    # from a level 25% too high, the level's fit comes back without a refresh
    problem.refresh_hyperelastic(p)
    v0 = problem.evaluate(up)["total"]
    out, v, n = em._fit_level(problem, up, v0, None, None)
    assert v < v0 and n > 5
    assert out["E_A_kPa"] / out["E_B_kPa"] == pytest.approx(up["E_A_kPa"] / up["E_B_kPa"], rel=1e-9)
    assert problem.evaluate(out)["nmi"] == pytest.approx(problem.evaluate(up)["nmi"], abs=1e-9)  # the level moves no pixel
    assert problem.evaluate(out)["force_rms_N"] < 0.5 * problem.evaluate(up)["force_rms_N"]
    # nothing better: the parameters given back
    same, v2, _ = em._fit_level(problem, out, -1e9, None, None)
    assert same == out and v2 == -1e9


@pytest.mark.parametrize("case,displacement_fall", [("hyper", 3.0), ("e-hyper", 2.0)])
def test_hidden_hyperelasticity_is_named_and_adding_it_fixes_the_model(tmp_path_factory, case, displacement_fall):
    """The truth is neo-Hookean (large deformation), pressed to 25% of the
    height: the force stiffens as the probe goes deeper and the linear baseline
    cannot follow it. The diagnosis names hyperelastic; with it the moduli come
    right and the error beyond the noise falls at least 3x.

    Measured on the committed meshes (2026-11-26, truth written again with the
    8-point rule beside the probe's outline): named first, pattern match 94%, the
    force stiffens 14%; moduli -2.0% and -9.0% (the baseline's E_A was +54%);
    the force error beyond the noise falls to the noise, the displacement's 4.1x.
    With the earlier 4-point truth: 33x and 4.3x, moduli -2.1% and -9.2%.

    On the soft ellipsoid (seed 26, 7.5 mm into 32 mm; 2026-11-26): named first
    (pattern match 85%, the force stiffens 6%), moduli -1.0% and -1.8% (the
    baseline's E_A was +61%), the force error beyond the noise falls to the
    noise, the displacement's 2.6x (0.82 -> 0.31 px): the effect's own channel,
    the force, falls more than 3x; the images' remaining 0.31 px is near the
    mesh error of this phantom's other cases (0.2-0.24 px for the correct
    model), so the displacement is held to 2x there."""
    exp = _make(tmp_path_factory, case)  # neo-Hookean truth pressed 7.5 mm (seeds 1, 26)
    d = diagnose(exp, candidates=("hyperelastic", "viscoelastic", "compressibility"), mesh_settings=ID_MESH)
    assert d.verdict == "hyperelastic", d.lines()
    c = d.candidate("hyperelastic")
    assert c.material and c.signature >= 0.6, d.lines()
    assert "stiffens" in c.evidence
    for region, err in _moduli_errors(c.parameters, read_truth(exp.path)["moduli_kPa"]).items():
        assert abs(err) < 0.10, (region, err, d.lines())
    assert c.misfit["force_excess_N"] < d.baseline.misfit["force_excess_N"] / 3.0, d.lines()
    assert c.misfit["displacement_excess_px"] < d.baseline.misfit["displacement_excess_px"] / displacement_fall, \
        d.lines()


def test_a_poisson_ratio_near_the_models_is_no_finding():
    """The mesh error alone pulls a fitted Poisson's ratio from 0.49 to
    0.482-0.487 on data with nothing missing: within 0.02 of the model's it is
    reported, with the reason, and is not material; 0.45 is a finding."""
    from app.core.diagnose import Candidate
    from app.core.effects.compressibility import negligible

    assert negligible(0.482, 0.49) and negligible(0.4995, 0.49)
    assert negligible(0.45, 0.49) == "" and negligible(0.3, 0.49) == ""
    c = Candidate("compressibility", ("compressibility",), {"nu": 0.482}, {}, {"chi2": 1.0}, 1, 55.4,
                  "the tissue changes volume", negligible=negligible(0.482, 0.49))
    assert "no finding" in c.explanation and c.explanation.endswith("so it is not a verdict)")
    assert c.to_json_dict()["negligible"] == c.negligible and c.to_json_dict()["material"] is False


def test_an_inclusion_is_credited_only_with_what_it_explains_beyond_both_references():
    """The inclusion, on a mesh of its own, is scored from the current model on
    that mesh when the mesh alone fits better (the mesh's gain is not the
    inclusion's), else from the current model (an inclusion under the probe
    that makes up for a worse mesh has not explained the measurements: on a
    paper-size sliding-bottom case with nine frames it outscored sliding-bottom
    that way, +12,492 against +11,917, with the larger remaining error)."""
    from app.core.diagnose import Candidate, scoring_reference

    def cand(effect, chi2, reference=None):
        return Candidate(effect, (effect,), {}, {}, {"chi2": chi2}, 4, reference=reference)

    base = cand("", 1000.0)
    assert scoring_reference(base, cand("inclusion", 500.0, {"chi2": 900.0}))["chi2"] == 900.0  # better mesh
    assert scoring_reference(base, cand("inclusion", 500.0, {"chi2": 1100.0})) is base.misfit  # worse mesh
    assert scoring_reference(base, cand("sliding-bottom", 500.0)) is base.misfit


def test_a_near_tie_goes_to_the_effect_whose_pattern_the_misfit_has():
    """Scores and pattern matches of the paper-size cases with three frames. On
    sliding-bottom data the inclusion scored +2,873 at 92% and sliding-bottom
    +2,783 at 96%: a near tie, so the verdict is sliding-bottom and the
    inclusion its rival. On probe-slip data compressibility (+1,569, 79%) stays
    the verdict over probe-slip (+1,415, 78%): within the margin. A runner-up
    that is not a finding, or scores well below the best, is no rival and
    changes nothing."""
    from app.core.diagnose import NEAR_TIE, Candidate, Diagnosis, NoiseModel, choose_verdict

    def diag(*cands):
        cs = [Candidate(e, (e,), {}, {}, {"chi2": 1.0}, 1, score, "", material=mat, signature=sig)
              for e, score, mat, sig in cands]
        base = Candidate("", (), {}, {}, {"chi2": 1.0, "force_rms_N": 0.02, "displacement_rms_px": 0.5})
        return Diagnosis("x", base, cs, choose_verdict(cs), NoiseModel(0.02, 10, 0.1, 10), 1.0)

    d = diag(("inclusion", 2873.0, True, 0.924), ("sliding-bottom", 2783.0, True, 0.965),
             ("compressibility", 2317.0, False, 0.905))
    assert d.verdict == "sliding-bottom" and d.rival == "inclusion"
    advice = d.tie_advice()
    assert "inclusion scores slightly better (+2,873 against +2,783)" in advice
    assert "the verdict goes to sliding-bottom" in advice and "specimen slides on the table" in advice
    assert d.to_json_dict()["rival"] == "inclusion" and d.lines()[-1].startswith("near tie: inclusion")
    assert d.lines()[0].startswith("current model: baseline; force misfit 0.0200 N")
    inc = {"name": "I", "center_mm": [57.5, 45.0, 85.2], "radius_mm": 5.4}  # a current model with an inclusion
    d.baseline = Candidate("", ("inclusion",), {}, {}, dict(d.baseline.misfit), inclusion=inc)
    assert d.lines()[0].startswith("current model: inclusion (I centred at (57.5, 45.0, 85.2) mm, radius 5.4 mm);")
    d = diag(("compressibility", 1569.0, True, 0.792), ("probe-slip", 1415.0, True, 0.778))
    assert d.verdict == "compressibility" and d.rival == "probe-slip"
    assert "probe-slip scores nearly as well (+1,415 against +1,569)" in d.tie_advice()
    # no near tie: not a finding, or too far below
    d = diag(("inclusion", 2873.0, True, 0.5), ("sliding-bottom", 2783.0, False, 0.97))
    assert d.verdict == "inclusion" and d.rival == ""
    d = diag(("inclusion", 2873.0, True, 0.5), ("sliding-bottom", 0.75 * 2873.0, True, 0.97))
    assert d.verdict == "inclusion" and d.rival == "" and NEAR_TIE > 0.75
    d = diag(("viscoelastic", 217807.0, True, 0.99), ("compressibility", 326.0, True, 0.35))
    assert d.rival == "" and d.tie_advice() == "" and d.to_json_dict()["rival"] is None
    assert diag(("compressibility", 100.0, False, 0.9)).verdict == "none"
    # a third finding of the near tie is named too (blind slip+31000 rerun on a fresh inclusion mesh: the
    # hidden slip third at +1,057 behind an inclusion, +1,146, and compressibility, +1,108)
    d = diag(("inclusion", 1146.0, True, 0.96), ("compressibility", 1108.0, True, 0.95),
             ("probe-slip", 1057.0, True, 0.98))
    assert d.verdict == "inclusion" and d.rival == "compressibility"
    advice = d.tie_advice()
    assert "; probe-slip (+1,057) is in the near tie too: these measurements barely separate them." in advice, advice
    assert "Use what you know of the setup: an undescribed inclusion" in advice and ", or probe slides on the " \
        "surface?" in advice, advice


def test_a_near_tie_of_two_effects_is_settled_by_fitting_them_together():
    """Paper size, probe slip hidden (seed 103): compressibility (Poisson's ratio
    0.468, chi2 2,192.1, +1,569) outscored probe-slip (chi2 2,346.4, +1,415) with
    the pattern match a tie. Fitted together (chi2 2,114.0), Poisson's ratio came
    back to 0.480, no finding, while the slip still earned its parameter: the
    verdict is probe-slip, compressibility its rival. A joint fit in which the
    runner-up adds less than its parameter costs leaves the verdict where it was;
    one in which neither or both yield leaves it to the pattern match."""
    from app.core.diagnose import Candidate, Diagnosis, NoiseModel, TieBreak, choose_verdict, yields

    lnN = math.log(1481 + 282)

    def cand(effect, nu, chi2, score=0.0, sig=None, n=1):
        return Candidate(effect, (effect,), {} if nu is None else {"nu": nu}, {}, {"chi2": chi2}, n, score, "",
                         material=True, signature=sig)

    comp, slip = cand("compressibility", 0.468, 2192.1, 1569.0, 0.792), cand("probe-slip", None, 2346.4, 1414.8, 0.778)
    joint = cand("compressibility+probe-slip", 0.480, 2114.0, n=2)
    why = yields(comp, slip, joint, lnN, 0.49)
    assert "0.480 with probe-slip" in why and "no finding" in why
    assert yields(slip, comp, joint, lnN, 0.49) == ""
    tb = TieBreak(("compressibility", "probe-slip"), joint, {"compressibility": why, "probe-slip": ""})
    assert tb.winner == "probe-slip" and choose_verdict([comp, slip]) == "compressibility"
    base = Candidate("", (), {}, {}, {"chi2": 3768.7, "force_rms_N": 0.02, "displacement_rms_px": 0.88})
    d = Diagnosis("x", base, [comp, slip], choose_verdict([comp, slip], tb), NoiseModel(0.02, 1481, 0.165, 282), 1.0,
                  tie_break=tb)
    assert d.verdict == "probe-slip" and d.rival == "compressibility"
    assert f"fitted together, {why}, so the verdict goes to probe-slip" in d.tie_advice()
    js = d.to_json_dict()["tie_break"]
    assert js["verdict"] == "probe-slip" and js["yields"] == {"compressibility": why, "probe-slip": None}
    assert js["chi2"] == 2114.0 and js["parameters"] == {"nu": 0.48}
    # the same data with the inclusion scan of 4c967ea: a soft sphere under the probe tied
    # too (+1,438, 75%). Compressibility is out by the joint fit; between the inclusion
    # and probe-slip the pattern match decides (78% against 75%); the rival is the one
    # that did not yield
    incl = Candidate("inclusion", ("inclusion",), {}, {}, {"chi2": 2100.0}, 4, 1438.2, "", material=True,
                     signature=0.752)
    cs = [comp, incl, slip]
    d = Diagnosis("x", base, cs, choose_verdict(cs, tb), NoiseModel(0.02, 1481, 0.165, 282), 1.0, tie_break=tb)
    assert choose_verdict(cs) == "compressibility" and d.verdict == "probe-slip" and d.rival == "inclusion"
    advice = d.tie_advice()
    assert advice.startswith("inclusion scores slightly better (+1,438 against +1,415); compressibility (+1,569) "
                             "yields to probe-slip: fitted together, Poisson's ratio comes out at 0.480"), advice
    assert "the verdict goes to probe-slip, whose pattern the misfit has more closely (78% against 75%)" in advice
    # the runner-up adds less than its parameter costs on top of the best: the best stays
    joint = cand("compressibility+probe-slip", 0.468, 2192.1 - 0.5 * lnN, n=2)
    why = yields(slip, comp, joint, lnN, 0.49)
    assert "probe-slip lowers chi2 by 4 on top of compressibility, less than its parameters cost (7)" == why
    assert yields(comp, slip, joint, lnN, 0.49) == ""
    assert choose_verdict([comp, slip], TieBreak(("compressibility", "probe-slip"), joint,
                                                 {"compressibility": "", "probe-slip": why})) == "compressibility"
    # neither yields (both effects there), or both: the pattern match decides
    for ys in ({"compressibility": "", "probe-slip": ""}, {"compressibility": "a", "probe-slip": "b"}):
        tb = TieBreak(("compressibility", "probe-slip"), joint, ys)
        assert tb.winner == "" and choose_verdict([comp, slip], tb) == "compressibility"


def test_when_the_two_best_of_a_near_tie_each_yield_the_third_is_fitted_with_the_best(monkeypatch):
    """Blind paper-size seed 22103 (probe slip hidden; bench/paper_effects.py
    --cases slip --seed-offset 22000): compressibility +1,438 (pattern 94.8%), a
    soft sphere under the probe +1,392 (94.1%) and probe-slip +1,324 (96.8%).
    Compressibility and the sphere, fitted together, each yielded to the other,
    and the pattern match gave compressibility: probe-slip's match fell just short
    of SIGNATURE_MARGIN above it. The third finding is now fitted with the best
    one; there compressibility yields to the slip, so it is out, and between the
    sphere and the slip the pattern match gives probe-slip. When that second
    pair does not tell either, the first pair's fit stands."""
    from types import SimpleNamespace

    import app.core.diagnose as dg
    from app.core.diagnose import Candidate, Diagnosis, NoiseModel, TieBreak, choose_verdict

    def cand(effect, score, sig, **kw):
        return Candidate(effect, (effect,), {}, {}, {"chi2": 3270.0 - score}, 1, score, "", material=True,
                         signature=sig, **kw)

    problem = SimpleNamespace(effects=())
    comp, slip = cand("compressibility", 1437.9, 0.948), cand("probe-slip", 1323.5, 0.968)
    incl = cand("inclusion", 1391.7, 0.941, problem=problem, inclusion={"name": "I", "center_mm": [43.1, 45.0, 89.1],
                                                                       "radius_mm": 6.4})
    ranked = [comp, incl, slip]
    mutual = {"compressibility": "Poisson's ratio comes out at 0.478 with inclusion, within 0.02 of the model's "
                                 "0.49 (no finding)",
              "inclusion": "inclusion lowers chi2 by 23 on top of compressibility, less than its parameters cost (30)"}
    slip_wins = {"compressibility": "Poisson's ratio comes out at 0.486 with probe-slip, within 0.02 of the model's "
                                    "0.49 (no finding)", "probe-slip": ""}
    fitted = []

    def fit_pair(a, b, *args):
        fitted.append((a.effect, b.effect))
        joint = Candidate(f"{a.effect}+{b.effect}", (), {}, {}, {"chi2": 1800.0}, 2)
        return TieBreak((a.effect, b.effect), joint, mutual if b.effect == "inclusion" else outcome[0])

    monkeypatch.setattr(dg, "_fit_pair", fit_pair)
    outcome = [slip_wins]
    assert choose_verdict(ranked, TieBreak(("compressibility", "inclusion"), None, mutual)) == "compressibility"
    tb = dg._tie_break(ranked, problem, None, None, 200, lambda s: None, None)
    assert fitted == [("compressibility", "inclusion"), ("compressibility", "probe-slip")]
    assert tb.effects == ("compressibility", "probe-slip") and tb.winner == "probe-slip"
    assert tb.before.effects == ("compressibility", "inclusion") and tb.before.yields == mutual
    d = Diagnosis("x", Candidate("", (), {}, {}, {"chi2": 3270.0}), ranked, choose_verdict(ranked, tb),
                  NoiseModel(0.02, 1481, 0.117, 242), 1.0, tie_break=tb)
    assert d.verdict == "probe-slip" and d.rival == "inclusion"
    advice = d.tie_advice()
    assert advice.startswith("inclusion scores slightly better (+1,392 against +1,324); compressibility and "
                             "inclusion, fitted together first, each yield to the other; compressibility (+1,438) "
                             "yields to probe-slip: fitted together, Poisson's ratio comes out at 0.486"), advice
    assert "the verdict goes to probe-slip, whose pattern the misfit has more closely (97% against 94%)" in advice
    js = d.to_json_dict()["tie_break"]
    assert js["verdict"] == "probe-slip" and js["before"]["effects"] == ["compressibility", "inclusion"]
    assert js["before"]["verdict"] is None and js["before"]["before"] is None
    # the second pair does not tell either (each yields, or neither): the first pair's fit stands
    for ys in ({"compressibility": "a", "probe-slip": "b"}, {"compressibility": "", "probe-slip": ""}):
        outcome[0], fitted[:] = ys, []
        tb = dg._tie_break(ranked, problem, None, None, 200, lambda s: None, None)
        assert len(fitted) == 2 and tb.effects == ("compressibility", "inclusion") and tb.before is None
        assert choose_verdict(ranked, tb) == "compressibility"
    # two findings only, or a first pair with a winner: one joint fit
    fitted[:] = []
    assert dg._tie_break([comp, incl], problem, None, None, 200, lambda s: None, None).before is None
    assert fitted == [("compressibility", "inclusion")]
    outcome[0], fitted[:] = slip_wins, []
    assert dg._tie_break([comp, slip, incl], problem, None, None, 200, lambda s: None, None).winner == "probe-slip"
    assert fitted == [("compressibility", "probe-slip")]


def test_a_hyperelastic_candidate_keeps_the_correction_of_its_best_start(monkeypatch):
    """A hyperelastic model evaluates with the nonlinear correction its last fit
    computed. With several starts (compressibility 2, viscoelastic 6) the best
    start's correction is put back, not the last start's: with the last one's,
    blind seed 22205 (a neo-Hookean truth with Poisson's ratio 0.45) scored
    compressibility, fitted at nu 0.449 with the true moduli, with a force misfit
    of 0.063 N against the noise's 0.02."""
    import app.core.diagnose as dg
    from app.core.effects.model import FitResult

    class Problem:
        effects = ("hyperelastic", "compressibility")
        state = None
        restored = []

        def hyperelastic_state(self):
            return self.state

        def restore_hyperelastic(self, state):
            self.restored.append(state)
            self.state = state

    cp = Problem()

    def fit_ml(problem, lik, start, *args):
        problem.state = f"correction at nu {start['nu']}"  # each fit refreshes the correction at its optimum
        return FitResult(dict(start), {}, {0.45: 1.0, 0.35: 5.0}[start["nu"]], 10, 0.0)

    monkeypatch.setattr(dg, "_fit_ml", fit_ml)
    res = dg._fit_polished(cp, None, [{"nu": 0.45}, {"nu": 0.35}], None, 300, lambda s: None, "compressibility")
    assert res.parameters == {"nu": 0.45} and cp.state == "correction at nu 0.45"
    assert cp.restored == ["correction at nu 0.45"]
    # one start, or a linear model: nothing to put back
    cp.restored.clear()
    dg._fit_polished(cp, None, [{"nu": 0.35}], None, 300, lambda s: None, "compressibility")
    assert cp.restored == [] and cp.state == "correction at nu 0.35"
    Problem.effects = ("compressibility",)
    dg._fit_polished(cp, None, [{"nu": 0.45}, {"nu": 0.35}], None, 300, lambda s: None, "compressibility")
    assert cp.restored == []


def test_an_inclusion_that_vanishes_when_fitted_with_the_other_effect_yields():
    """Paper size, sliding-bottom hidden (seed 2102, bench/paper_effects.py
    --seed-offset 2000): a stiff sphere located under the probe (2.6 times its
    tissue, chi2 2,606.6, +2,789) tied with sliding-bottom (chi2 2,678.5,
    +2,740). Fitted together on the inclusion's mesh (chi2 2,650.8), the
    sphere's modulus came out at 17.2 kPa in B's 17.9: the inclusion is no longer
    there, while sliding-bottom raised chi2 on top of it (a switch is not nested
    in the model without it). Each yields to the other, so the pattern match
    decides, and the advice says both."""
    from dataclasses import replace

    from app.core.diagnose import Candidate, Diagnosis, NoiseModel, TieBreak, choose_verdict, yields
    from app.core.effects.inclusion import surroundings

    lnN = math.log(1481 + 274)
    place = {"name": "I", "center_mm": [43.1, 45.0, 85.2], "radius_mm": 6.4}
    inc = Candidate("inclusion", ("inclusion",), {"E_B_kPa": 16.15, "E_A_kPa": 77.62, "E_I_kPa": 41.98}, {},
                    {"chi2": 2606.6}, 4, 2789.3, "", place, material=True, signature=0.86)
    slide = Candidate("sliding-bottom", ("sliding-bottom",), {"E_B_kPa": 17.72, "E_A_kPa": 66.89}, {},
                      {"chi2": 2678.5}, 1, 2739.8, "", material=True, signature=0.82)
    # sliding-bottom fitted on the inclusion's mesh, the sphere's tets given back to B
    alone = Candidate("sliding-bottom", ("sliding-bottom",), {}, {}, {"chi2": 2702.0}, 1)
    joint = Candidate("inclusion+sliding-bottom", ("sliding-bottom", "inclusion"),
                      {"E_B_kPa": 17.90, "E_A_kPa": 63.40, "E_I_kPa": 17.16}, {}, {"chi2": 2650.8}, 5,
                      inclusion=place)
    # the sphere takes the place of B and a little of A
    shares = surroundings(place, read_experiment(ROOT / "resources" / "demo").specimen)
    assert shares == {0: pytest.approx(0.937, abs=0.001), 1: pytest.approx(0.063, abs=0.001)}
    replaced = {"B": shares[0], "A": shares[1]}
    why_inc = yields(inc, alone, joint, lnN, 0.49, replaced)
    assert why_inc == ("with sliding-bottom, an inclusion that changes the stiffness of the tissue it replaces by a "
                       "factor 1.13 on average (17.2 kPa in place of B 17.9 kPa (94%), A 63.4 kPa (6%)) is no "
                       "finding: the mesh error alone fits a located region within a factor 1.5 of its "
                       "surroundings"), why_inc
    assert yields(inc, alone, joint, lnN, 0.49) == ""  # without what it replaces: the chi2 alone decides
    why_slide = yields(slide, inc, joint, lnN, 0.49, replaced)
    assert why_slide == "sliding-bottom raises chi2 by 44 on top of inclusion"
    tb = TieBreak(("inclusion", "sliding-bottom"), joint, {"inclusion": why_inc, "sliding-bottom": why_slide})
    assert tb.winner == "" and choose_verdict([inc, slide], tb) == "inclusion"
    base = Candidate("", (), {}, {}, {"chi2": 5425.7, "force_rms_N": 0.02, "displacement_rms_px": 1.75})
    d = Diagnosis("x", base, [inc, slide], choose_verdict([inc, slide], tb), NoiseModel(0.02, 1481, 0.24, 274), 1.0,
                  tie_break=tb)
    assert d.rival == "sliding-bottom"
    assert f"fitted together, each yields to the other ({why_inc}; {why_slide})" in d.tie_advice()
    # the sphere still there with the other effect (twice its tissue's modulus): the inclusion stands
    still = replace(joint, parameters={**joint.parameters, "E_I_kPa": 2 * 17.9})
    assert yields(inc, alone, still, lnN, 0.49, replaced) == ""


def test_a_located_inclusion_does_not_win_a_near_tie_by_its_pattern():
    """Blind seed 23012 (paper size, a 30 x 14 mm probe face slipping, nothing
    else hidden): probe-slip +1,012 with the pattern at 90% and a soft stand-in
    sphere under the probe +989 at 95% each yielded to the other, and the pattern
    match gave the inclusion. The sphere is placed where the misfit is, so its
    pattern follows the misfit by construction: it no longer wins by it. The
    pattern still takes a verdict from the inclusion (the paper-size
    sliding-bottom case), and an inclusion that scores best keeps it."""
    from dataclasses import replace

    from app.core.diagnose import Candidate, Diagnosis, NoiseModel, TieBreak, choose_verdict, wins_by_pattern

    place = {"name": "I", "center_mm": [46.7, 45.0, 88.8], "radius_mm": 6.4}
    slip = Candidate("probe-slip", ("probe-slip",), {"E_B_kPa": 17.78, "E_A_kPa": 64.13}, {}, {"chi2": 2083.5}, 1,
                     1012.4, "", material=True, signature=0.896)
    inc = Candidate("inclusion", ("inclusion",), {"E_B_kPa": 18.05, "E_A_kPa": 60.81, "E_I_kPa": 11.90}, {},
                    {"chi2": 1829.7}, 4, 989.1, "", place, material=True, signature=0.946)
    joint = Candidate("probe-slip+inclusion", ("probe-slip", "inclusion"),
                      {"E_B_kPa": 17.98, "E_A_kPa": 61.82, "E_I_kPa": 16.41}, {}, {"chi2": 1828.5}, 5, inclusion=place)
    tb = TieBreak(("probe-slip", "inclusion"), joint,
                  {"probe-slip": "probe-slip lowers chi2 by 1 on top of inclusion, less than its parameters cost (7)",
                   "inclusion": "with probe-slip, an inclusion 0.91 times as stiff as the tissue it replaces (B: 16.4 "
                                "against 18.0 kPa) is no finding"})
    assert tb.winner == "" and not wins_by_pattern(inc, slip)
    assert choose_verdict([slip, inc], tb) == "probe-slip"
    base = Candidate("", (), {}, {}, {"chi2": 3103.4, "force_rms_N": 0.02, "displacement_rms_px": 0.67})
    d = Diagnosis("x", base, [slip, inc], choose_verdict([slip, inc], tb), NoiseModel(0.0201, 1481, 0.17, 238), 1.0,
                  tie_break=tb)
    assert d.rival == "inclusion"
    assert ("the inclusion's closer pattern (95% against 90%) does not decide, as it was placed where the misfit is"
            in d.tie_advice()), d.tie_advice()
    # when the joint fit put the inclusion out, the fit decided, not the rule on its pattern
    out = TieBreak(tb.effects, joint, {"probe-slip": "", "inclusion": tb.yields["inclusion"]})
    d.tie_break = out
    assert out.loser == "inclusion" and "does not decide" not in d.tie_advice(), d.tie_advice()
    # another effect still wins by its pattern, over the inclusion or not
    slide = replace(slip, effect="sliding-bottom", effects=("sliding-bottom",), score=950.0, signature=0.97)
    assert wins_by_pattern(slide, inc) and choose_verdict([inc, slide]) == "sliding-bottom"
    assert choose_verdict([slip, slide]) == "sliding-bottom"
    # an inclusion that scores best keeps the verdict
    first = replace(inc, score=1100.0)
    assert choose_verdict([first, slip], tb) == "inclusion"


def test_a_located_inclusion_close_to_its_surroundings_modulus_is_no_finding():
    """On data with nothing hidden the located sphere changes the modulus of the
    tissue it replaces by a factor 1.06-1.43 where it could matter (14 diagnoses,
    docs/model-check.md "The inclusion locator"); on a 100 x 70 x 80 mm phantom
    one 0.87 times as stiff as B removed 88% of the error beyond the noise and
    was the verdict before this rule. A hidden sphere 3.3 times stiffer was fitted
    at 2.07-2.25 times. A sphere that extends a stiff region into soft tissue
    (the test phantom's, 41 kPa over A's 52 and B's 15) changes the soft part."""
    from app.core.effects.inclusion import NEGLIGIBLE_RATIO, negligible

    why = negligible(6.89, [("B", 1.0, 7.96)])
    assert why.startswith("an inclusion 0.87 times as stiff as the tissue it replaces (B: 6.9 against 8.0 kPa) is "
                          "no finding"), why
    for ratio in (0.7, 0.94, 1.12, 1.43):
        assert negligible(18.0 * ratio, [("B", 1.0, 18.0)])
    for ratio in (2.07, 2.25, 0.16, 0.5):  # hidden stiff spheres; soft ones absorbing a compressibility
        assert negligible(18.0 * ratio, [("B", 1.0, 18.0)]) == ""
    assert negligible(18.0 * NEGLIGIBLE_RATIO, [("B", 1.0, 18.0)]) == ""
    # straddling: mostly B, a little A (seed 9106: 0.92 times B over 91% of it) is no finding;
    # extending A (52 kPa) into B (15 kPa) at 41 kPa is one
    why = negligible(16.6, [("B", 0.91, 18.0), ("A", 0.09, 63.0)])
    assert why.startswith("an inclusion that changes the stiffness of the tissue it replaces by a factor 1.21 on "
                          "average (16.6 kPa in place of B 18.0 kPa (91%), A 63.0 kPa (9%)) is no finding"), why
    assert negligible(41.4, [("A", 0.6, 52.3), ("B", 0.4, 15.0)]) == ""


def test_a_located_inclusion_fitted_at_a_bound_of_its_modulus_is_no_finding():
    """Blind paper seeds 21014 and 21017 (the probe slipping over a sphere; the slip
    added): the next diagnoses made the inclusion the verdict at a bound of its
    modulus, 0.1 kPa 26 mm from the hidden sphere, and 10,000 kPa 41 mm from it.
    The 76 other inclusion verdicts recorded at paper size were fitted at 3.0-487
    kPa; the five other fits at a bound stood in for other effects.
    Scored +144 and +465, such a sphere is now no finding, whatever it removes."""
    from app.core.diagnose import Candidate
    from app.core.effects.inclusion import at_bound, negligible

    why = negligible(1e4, [("B", 1.0, 18.3)])
    assert why.startswith("its modulus went to the fit's upper bound (10,000 kPa: a rigid body), where a sphere "
                          "stands for a pattern it cannot represent"), why
    assert "if a hard body (bone, a calcification, an instrument) is plausible there, add the inclusion" in why
    why = negligible(0.1, [("B", 0.7, 18.1), ("A", 0.3, 63.9)])
    assert why.startswith("its modulus went to the fit's lower bound (0.1 kPa: as soft as a fluid)"), why
    assert "a fluid-filled cyst" in why
    # the right verdicts' extremes: the 10 kPa sphere of 21017 fitted at 3.0, the out-of-view one at 487
    for e in (3.02, 487.14, 9000.0, 0.2):
        assert at_bound(e) == "" and negligible(e, [("B", 1.0, 18.0)]) == "", e
    c = Candidate("inclusion", ("inclusion",), {"E_I_kPa": 1e4}, {}, {"chi2": 1800.0}, 4, 465.0, "a stiffer region",
                  negligible=negligible(1e4, [("B", 1.0, 18.3)]))
    assert "(but its modulus went to the fit's upper bound" in c.explanation and c.explanation.endswith(
        "so it is not a verdict)"), c.explanation


def test_a_verdict_of_none_says_why_and_names_an_effect_that_came_close():
    """Numbers from the paper-size hidden Poisson's ratio of 0.40 with three frames
    (seed 1104, bench/paper_effects.py --seed-offset 1000): compressibility fitted
    nu 0.391, scored +5,680 and put the moduli within 5% of the truth (the
    baseline's A was off by 70%), but removed 29% of the error beyond the noise
    (2.07 -> 1.48 px). Until the chi2 rule (is_material, the test above) that made
    the verdict none; here the candidates are given as not material, as one that
    also lowered the images' chi2 by less than 2 per component would be. The
    verdict's text must not say that nothing lowers the misfit by more than its
    parameters cost; it names the effect that came close, with the moduli it
    gives. An effect that removes less than NEAR_MISS_FRACTION, or fits no
    physical change, is not named."""
    from app.core.diagnose import (MATERIAL_FRACTION, NEAR_MISS_FRACTION, Candidate, Diagnosis, NoiseModel,
                                   choose_verdict)

    def mis(chi2, excess_px):
        return {"chi2": chi2, "force_rms_N": 0.0197, "displacement_rms_px": 1.0, "force_excess_N": 0.006,
                "force_floor_N": 0.0188, "displacement_excess_px": excess_px, "displacement_floor_px": 0.19}

    base = Candidate("", (), {"E_B_kPa": 15.54, "E_A_kPa": 107.03}, {}, mis(8665.7, 2.074))
    noise = NoiseModel(0.02, 1481, 0.236, 318)

    def diag(cands):
        return Diagnosis("x", base, cands, choose_verdict(cands), noise, 1.0)

    comp = Candidate("compressibility", ("compressibility",), {"E_B_kPa": 18.02, "E_A_kPa": 60.05, "nu": 0.391}, {},
                     mis(2978.5, 1.478), 1, 5679.7, "volume")
    incl = Candidate("inclusion", ("inclusion",), {"E_B_kPa": 16.4, "E_A_kPa": 95.4}, {}, mis(6223.7, 1.638), 4,
                     1974.0, "a region", reference=mis(8100.0, 1.9))
    hyper = Candidate("hyperelastic", ("hyperelastic",), {}, {}, mis(69577.7, 5.09), 1, -60919.5, "stiffens")
    d = diag([comp, incl, hyper])
    assert d.verdict == "none" and 1 - 1.478 / 2.074 < MATERIAL_FRACTION
    assert [(c.effect, round(f, 3)) for c, f in d.near_misses()] == [("compressibility", 0.287)]
    text = d.none_text()
    assert "lowers the misfit by more than its parameters cost" not in text.split(". But")[0]
    assert "But compressibility comes close" in text and "(score +5,680)" in text and "removes 29%" in text
    assert "B 16% higher (18.0 against 15.5 kPa), A 44% lower (60.0 against 107.0 kPa) in the fits to the tracked blocks" in text and "about 2% apart" in text
    assert "inclusion" not in text  # 1.9 -> 1.638 px on its own mesh: 14%, below NEAR_MISS_FRACTION
    assert d.to_json_dict()["near_misses"] == [{"effect": "compressibility", "explained": 0.287}]
    assert f"why: {text}" in d.lines()
    # the same fit of a Poisson's ratio within 0.02 of the model's: no finding, not named
    neg = Candidate("compressibility", ("compressibility",), {"nu": 0.484}, {}, mis(2978.5, 1.478), 1, 5679.7, "",
                    negligible="Poisson's ratio 0.484 is within 0.02 of the model's")
    assert diag([neg, incl, hyper]).near_misses() == []
    # two effects close (paper-size probe slip, seed 1103): both named, best score first
    slip = Candidate("probe-slip", ("probe-slip",), {"E_B_kPa": 17.7}, {}, mis(2900.0, 1.53), 0, 5000.0, "slides")
    two = diag([comp, slip, hyper]).none_text()
    assert "But compressibility (score +5,680, 29% removed) and probe-slip (score +5,000, 26%) come close" in two
    # nothing earns its parameters: the plain sentence, which says what the current model leaves beyond the noise
    plain = diag([hyper]).none_text()
    assert plain.startswith("No candidate effect lowers the misfit by more than its parameters")
    assert "in the displacement 2.07 px, 10.9 times its noise floor" in plain and "two effects that mask" in plain
    assert "as well as the noise allows" not in plain and "force" not in plain  # the force's 0.006 N is noise
    quiet = Candidate("", (), base.parameters, {}, mis(8665.7, 0.2))  # 1.05 times the floor: nothing left
    assert Diagnosis("x", quiet, [hyper], "none", noise, 1.0).none_text() == (
        "No candidate effect lowers the misfit by more than its parameters cost: the current model explains the "
        "data as well as the noise allows")
    # a verdict: no text, no near misses
    found = Candidate("compressibility", ("compressibility",), {"nu": 0.391}, {}, mis(2978.5, 0.5), 1, 5679.7, "",
                      material=True)
    assert diag([found, hyper]).none_text() == "" and diag([found, hyper]).near_misses() == []
    assert NEAR_MISS_FRACTION < MATERIAL_FRACTION


def test_a_finding_on_a_thin_margin_is_confirmed_on_a_finer_mesh_or_dropped():
    """The first mesh's numbers are blind seed 30205's (paper size, nothing
    hidden): the current model's displacement error beyond the noise was 0.266 px
    against a floor of 0.150 (1.77 times, under CONFIRM_BELOW), and a probe slip
    removed 32% of it (0.180 px): material by the displacement alone, the verdict.
    The finer mesh's are given here (that seed's own finer-mesh run was made on
    the truth's mesh, and is withdrawn: docs/model-check.md): when the error there
    is under its floor and the slip loses, the verdict is none and the why line
    says so with those figures. A finding on a wide margin, one the force shows,
    an inclusion or a finding on a neo-Hookean model is not diagnosed again."""
    from dataclasses import replace

    from app.core.diagnose import (CONFIRM_BELOW, Candidate, Diagnosis, NoiseModel, choose_verdict,
                                   confirmed_verdict, thin_finding)
    from app.gui.models.modelcheck import verdict_parts

    def mis(chi2, excess_px, force_excess_N=0.006):
        return {"chi2": chi2, "force_rms_N": 0.0197, "displacement_rms_px": 0.4, "force_excess_N": force_excess_N,
                "force_floor_N": 0.0188, "displacement_excess_px": excess_px, "displacement_floor_px": 0.150}

    base = Candidate("", (), {"E_B_kPa": 24.86, "E_A_kPa": 79.05}, {}, mis(3000.0, 0.266))
    slip = Candidate("probe-slip", ("probe-slip",), {"E_B_kPa": 24.9}, {}, mis(2800.0, 0.180), 1, 181.0, "slides",
                     material=True)
    comp = Candidate("compressibility", ("compressibility",), {"nu": 0.47}, {}, mis(2700.0, 0.250), 1, 279.0,
                     "volume")
    assert 0.266 / 0.150 < CONFIRM_BELOW and thin_finding(base, slip)
    assert not thin_finding(base, comp)  # no finding
    assert not thin_finding(replace(base, misfit=mis(3000.0, 0.50)), slip)  # 3.3 times its floor: a wide margin
    # the force shows it (the current model's force error 3 times its floor, 90% of it removed)
    assert not thin_finding(replace(base, misfit=mis(3000.0, 0.266, force_excess_N=0.06)), slip)
    assert not thin_finding(base, replace(slip, effect="inclusion"))
    assert not thin_finding(replace(base, effects=("hyperelastic",)), slip)

    noise = NoiseModel(0.02, 1481, 0.236, 318)
    ranked = [comp, slip]
    assert choose_verdict(ranked) == "probe-slip"
    dropped = {"effects": ["probe-slip"], "verdict": "none", "confirmed": False, "scale": 0.7,
               "nodes": [2558, 6266], "ratio": 0.266 / 0.150, "excess_px": 0.133, "floor_px": 0.150,
               "candidates": {"probe-slip": {"score": -379.0, "material": False, "explained": -0.4, "unmet": ""}},
               "seconds": 72.0}
    verdict = confirmed_verdict(ranked, None, "probe-slip", dropped)
    assert verdict == "none"
    d = Diagnosis("x", base, ranked, verdict, noise, 1.0, confirmation=dropped)
    why = d.none_text()
    assert why.startswith("probe-slip (score +181, removing 32% of the error beyond the noise) was a finding on a "
                          "thin margin: the current model's error beyond the noise in the displacement was 1.77 "
                          "times its noise floor"), why
    assert ("Diagnosed again on a mesh 0.7 times the size (6,266 vertices against 2,558; 72 s), the current model's "
            "error beyond the noise is 0.133 px, under its floor of 0.150 px, and probe-slip scores -379. What it "
            "explained was the mesh's error, not the specimen's") in why
    assert f"why: {d.none_text(with_masked=False)}" in d.lines() and d.rival == ""
    # nothing left beyond the noise there (blind seed 34205 on a fresh mesh): said so, not as "0.000 px"
    flat = Diagnosis("x", base, ranked, verdict, noise, 1.0, confirmation={**dropped, "excess_px": 0.0})
    assert "the current model fits within the noise (its floor 0.150 px), and probe-slip scores -379" in \
        flat.none_text()
    assert d.to_json_dict()["confirmation"] == dropped
    assert Diagnosis.from_state(d.state()).confirmation == dropped
    assert verdict_parts(d)[1] == f". {why}."
    # borne out: the verdict stands, with a line that says so
    kept = {**dropped, "verdict": "probe-slip", "confirmed": True, "excess_px": 0.25,
            "candidates": {"probe-slip": {"score": 240.0, "material": True, "explained": 0.4, "unmet": ""}}}
    assert confirmed_verdict(ranked, None, "probe-slip", kept) == "probe-slip"
    d = Diagnosis("x", base, ranked, "probe-slip", noise, 1.0, confirmation=kept)
    line = next(x for x in d.lines() if x.startswith("confirmed: "))
    assert line.endswith("Diagnosed again on a mesh 0.7 times the size (6,266 vertices against 2,558; 72 s), "
                         "probe-slip is still a finding (score +240): it is not the mesh's"), line
    assert "Probe-slip (score +181" in verdict_parts(d)[1] and d.none_text() == ""
    # the finer mesh's diagnosis failed: the verdict stands, and the report says it is unconfirmed
    failed = {"effects": ["probe-slip"], "confirmed": None, "error": "fTetWild failed"}
    assert confirmed_verdict(ranked, None, "probe-slip", failed) == "probe-slip"
    d = Diagnosis("x", base, ranked, "probe-slip", noise, 1.0, confirmation=failed)
    assert any(x.startswith("not confirmed: probe-slip rests on a thin margin") and "fTetWild failed" in x
               for x in d.lines()), d.lines()
    # dropped, with another finding beside it: that one is the verdict where the finer mesh leaves the current
    # model's error beyond MATERIAL_MIN (1.5) times its floor (0.25 px on 0.150)
    other = replace(comp, material=True)
    assert confirmed_verdict([other, slip], None, "probe-slip", {**dropped, "excess_px": 0.25}, base) == \
        "compressibility"
    # within it (0.133 px on 0.150), nothing is left there to explain: a finding the force does not show falls too
    # (blind wide-face-slip+35000: a soft sphere that "explains little of the misfit" had become the verdict)
    assert confirmed_verdict([other, slip], None, "probe-slip", dropped, base) == "none"
    d = Diagnosis("x", base, [other, slip], "none", noise, 1.0, confirmation=dropped)
    assert d.none_text().split(". What it explained")[1].startswith(
        " was the mesh's error, not the specimen's; so, most likely, was what compressibility (score +279) explained, "
        "as the force does not show it"), d.none_text()
    # one the force shows stays (the current model's force error 0.06 N, 90% of it removed)
    force_base = replace(base, misfit=mis(3000.0, 0.266, force_excess_N=0.06))
    visco = replace(other, effect="viscoelastic", misfit=mis(2700.0, 0.250, force_excess_N=0.006))
    assert confirmed_verdict([visco, slip], None, "probe-slip", dropped, force_base) == "viscoelastic"


def test_the_confirmation_is_not_run_when_memory_is_short(visco, monkeypatch):
    """The confirmation's finer models take about CONFIRM_BYTES_PER_UNKNOWN per
    unknown of the current model (a blind wide phantom went from 3.6 to 9.2 GB).
    When that much is not free, nothing is built; the verdict stands, unconfirmed,
    and the report says why and what to do."""
    import app.core.diagnose as dg
    from app.core import memory

    exp, d0 = visco
    problem = d0.baseline.problem
    asked = []

    def can_hold(n, reserve=memory.RESERVE_BYTES):
        asked.append(n)
        return False

    def must_not_build(*a, **k):
        raise AssertionError("the finer model was built")

    monkeypatch.setattr(memory, "can_hold", can_hold)
    monkeypatch.setattr(memory, "available_bytes", lambda: 2.5e9)
    monkeypatch.setattr(dg, "_model_like", must_not_build)
    thin = [d0.candidate("viscoelastic")]
    with pytest.raises(dg.ElastoidError, match="memory is short: 2.5 GB left, about") as err:
        dg._confirmed(exp, (), thin, d0.baseline, problem, ID_MESH, None, d0.tracked, 200, lambda s: None, None)
    assert asked == [dg.CONFIRM_BYTES_PER_UNKNOWN * problem.fe.space.n_dofs]
    k = {"effects": ["viscoelastic"], "confirmed": None, "error": str(err.value)}
    d = dg.Diagnosis("x", d0.baseline, d0.candidates, "viscoelastic", d0.noise, 1.0, confirmation=k)
    line = next(x for x in d.lines() if x.startswith("not confirmed: "))
    assert "would have confirmed it was not run (memory is short: 2.5 GB left" in line
    assert dg._refused(k) and not dg._refused({**k, "error": "fTetWild failed"}) and not dg._refused(None)
    assert line.endswith("diagnose again where more memory is free (or with ELASTOID_MEMORY_GB higher, if it "
                         "capped the memory) to tell"), line


def test_short_of_memory_the_confirmation_first_lets_go_of_models_no_verdict_needs():
    """Before the finer mesh's models are built on a machine short of memory, the
    candidates that are no finding give up their fitted models (rebuilt if added),
    and so do the inclusion's models unless it is a finding; the findings keep
    theirs (one may be the verdict, identified from its model), as do the boundary
    effects (the masked-pair screen scans them), and the current model's
    factorization is released. The report's memory line says so."""
    from types import SimpleNamespace

    from app.core.diagnose import Candidate, _make_room, _memory_note

    released = []
    current = SimpleNamespace(release=lambda: released.append("current"))

    def cand(effect, score, material):
        return Candidate(effect, (effect,), {"E_B_kPa": 18.0}, {}, {"chi2": 1.0}, 1, score, "", material=material,
                         problem=SimpleNamespace(name=effect))

    slip, comp, visco, incl, slide = (cand("probe-slip", 180.0, True), cand("compressibility", 120.0, True),
                                      cand("viscoelastic", -14.0, False), cand("inclusion", 40.0, False),
                                      cand("sliding-bottom", 30.0, False))
    prep = SimpleNamespace(places=[("guess", 30.0, "model", "reference")])
    assert _make_room([slip, comp, visco, incl, slide], prep, current) is True
    assert slip.problem is not None and comp.problem is not None  # findings: either may be the verdict
    assert slide.problem is not None  # the masked-pair screen scans it if the verdict becomes none
    assert visco.problem is None and incl.problem is None and visco.fitted and incl.fitted  # rebuilt if added
    assert prep.places == [] and released == ["current"]
    found = cand("inclusion", 400.0, True)
    prep = SimpleNamespace(places=[("guess", 30.0, "model", "reference")])
    _make_room([found, slip], prep, current)
    assert found.problem is not None and len(prep.places) == 1
    note = _memory_note(None, 0, made_room=True)
    assert note.startswith("memory was short, so before the finer mesh's diagnosis, the fitted models of the "
                           "candidates that are no finding were let go"), note
    assert _memory_note(None, 0) == ""
    refused = _memory_note(None, 0, made_room=True, refused=True)
    assert "the finding on a thin margin was not diagnosed again on a finer mesh (see not confirmed). The results " \
           "are the same but for that confirmation" in refused, refused


def test_a_mesh_coarser_than_the_automatic_one_is_said():
    """On the paper's phantom with a 30 x 14 mm face the automatic sizes are 10
    and 2.0 mm; a 2.5 mm face edge gave a probe slip with nothing hidden on both
    blind seeds tried (23010, 23011). A diagnosis on a coarser mesh says so (the
    report's mesh: line, the JSON's mesh_note); on the automatic sizes or finer
    ones it says nothing."""
    from dataclasses import replace as dc_replace

    from app.core.diagnose import Candidate, Diagnosis, NoiseModel, coarse_mesh_note
    from app.core.mesh import MeshSettings, auto_settings

    exp = read_experiment(ROOT / "resources" / "demo")
    exp = dc_replace(exp, probe=dc_replace(exp.probe, face_mm=(30.0, 14.0)))
    auto = auto_settings(exp.specimen.size_mm, exp.probe.face_rect_mm(), exp.specimen.regions)
    assert (auto.edge_mm, auto.probe_edge_mm, auto.outline_edge_mm) == (10.0, 2.0, 1.0)
    note = coarse_mesh_note(exp, MeshSettings(edge_mm=10.0, probe_edge_mm=2.5, outline_edge_mm=1.0))
    assert note.startswith("the mesh is coarser than the automatic one (on the probe face 2.5 mm against 2 mm)")
    assert "mesh check" in note
    assert "elements 12 mm against 10 mm; on the probe face" in coarse_mesh_note(exp, MeshSettings(12.0, 2.5))
    # the outline at the face's size (None), as every automatic mesh had it before 2026-12-01
    assert "(along its outline 2 mm against 1 mm)" in coarse_mesh_note(exp, dc_replace(auto, outline_edge_mm=None))
    for finer in (None, auto, auto.with_scale(0.7), MeshSettings(edge_mm=10.0, probe_edge_mm=2.05, outline_edge_mm=1.0),
                  MeshSettings(edge_mm=10.0, probe_edge_mm=0.9)):  # a face finer than the outline's 1 mm
        assert coarse_mesh_note(exp, finer) == ""
    base = Candidate("", (), {"E_B_kPa": 18.0}, {}, {"chi2": 1.0, "force_rms_N": 0.02, "displacement_rms_px": 0.3})
    d = Diagnosis("x", base, [], "none", NoiseModel(0.02, 1481, 0.236, 318), 1.0, mesh_note=note)
    assert f"mesh: {note}" in d.lines() and d.to_json_dict()["mesh_note"] == note
    assert Diagnosis.from_state(d.state()).mesh_note == note


def test_a_chi2_that_falls_far_beyond_the_mesh_error_is_material():
    """Paper size with three frames (bench/paper_effects.py --seed-offset 1000, the
    misfits of its JSON): a hidden Poisson's ratio of 0.40 (seed 1104) fitted by
    compressibility removed only 29% of the RMS error beyond the noise, the rest in
    poorly tracked blocks under the probe, but lowered the images' chi2 from 7,033
    to 1,346 over 318 tracked components (17.9 each): material. A hidden probe slip
    (seed 1103): 26%, 4.5 per component: material. With no hidden effect, the
    demo's located inclusion (+199) lowered it by 0.99 per component and seed
    5106's (+132) by 0.57: not material, as before."""
    from app.core.diagnose import (MATERIAL_CHI2_PER_COMPONENT, MATERIAL_FRACTION, Candidate,
                                   chi2_drop_per_component, explained, is_material, materiality_note)

    def mis(chi2_force, chi2_images, excess_px, floor_px, n_images, force_excess_N=0.006, force_floor_N=0.0188):
        return {"chi2": chi2_force + chi2_images, "chi2_force": chi2_force, "chi2_images": chi2_images,
                "displacement_excess_px": excess_px, "displacement_floor_px": floor_px,
                "force_excess_N": force_excess_N, "force_floor_N": force_floor_N, "n_force": 1481,
                "n_images": n_images}

    nu_before, nu_after = mis(1632.5, 7033.1, 2.0743, 0.1919, 318), mis(1632.5, 1345.9, 1.4778, 0.1919, 318)
    assert explained(nu_before, nu_after)["displacement"] < MATERIAL_FRACTION
    assert chi2_drop_per_component(nu_before, nu_after)["displacement"] == pytest.approx(17.88, abs=0.01)
    assert is_material(nu_before, nu_after)
    note = materiality_note(nu_before, nu_after)
    assert "removes 29% of the error beyond the noise" in note and "by 17.9 per tracked displacement" in note
    slip_before, slip_after = mis(1520.6, 2625.0, 0.6724, 0.1584, 302), mis(1520.6, 1263.8, 0.5004, 0.1584, 302)
    assert is_material(slip_before, slip_after) and materiality_note(slip_before, slip_after)
    demo_before = mis(1405.6, 1039.6, 0.4795, 0.2188, 300, 0.0, 0.0207)
    demo_after = mis(1405.6, 742.0, 0.4228, 0.2188, 300, 0.0, 0.0207)
    assert chi2_drop_per_component(demo_before, demo_after)["displacement"] < MATERIAL_CHI2_PER_COMPONENT / 2
    assert not is_material(demo_before, demo_after) and materiality_note(demo_before, demo_after) == ""
    # its evidence says why it is no verdict, by both rules
    demo_inclusion = Candidate("inclusion", ("inclusion",), {}, {}, demo_after, 4, 199.0, "a stiffer region",
                               material=False)
    assert demo_inclusion.explanation.endswith(
        f"(but it removes less than 30% of the error beyond the noise and lowers the chi2 by less than "
        f"{MATERIAL_CHI2_PER_COMPONENT:g} per measurement, so it is not a verdict)")
    none_before = mis(1441.9, 960.8, 0.5534, 0.2020, 286, 0.0, 0.0204)
    none_after = mis(1441.9, 798.8, 0.5142, 0.2020, 286, 0.0, 0.0204)
    assert not is_material(none_before, none_after)
    # material by its share: no note; a misfit saved without the counts: the share alone decides
    assert materiality_note(nu_before, mis(1632.5, 700.0, 0.9, 0.1919, 318)) == ""
    old = {k: v for k, v in nu_after.items() if not k.startswith("n_")}
    assert chi2_drop_per_component({k: v for k, v in nu_before.items() if not k.startswith("n_")}, old) == {
        "force": None, "displacement": None}


def test_why_a_candidate_is_no_finding_says_what_it_did():
    """Blind paper-size seed 21003 (sliding-bottom and a Poisson's ratio of 0.4
    hidden at once; /tmp/s12 in docs/model-check.md): with compressibility added,
    sliding-bottom took the displacement error beyond the noise from 0.160 px to
    0.0 and lowered the images' chi2 from 454.8 to 337.2 over 242 components
    (0.49 each). Not material: the error was already within 1.5 times its floor
    (0.122 px), as a mesh's own error leaves it. The evidence used to say "it
    removes less than 30% of the error", which was false; it now says what the
    candidate did, and the verdict none says why nothing can be a finding here."""
    from app.core.diagnose import (MATERIAL_MIN, Candidate, Diagnosis, NoiseModel, choose_verdict, is_material,
                                   not_material_text)

    def mis(chi2_images, excess_px, force_excess_N=0.0043):
        return {"chi2": 1552.99 + chi2_images, "chi2_force": 1552.99, "chi2_images": chi2_images,
                "force_rms_N": 0.0201, "displacement_rms_px": 0.5, "displacement_excess_px": excess_px,
                "displacement_floor_px": 0.1222, "force_excess_N": force_excess_N, "force_floor_N": 0.0196,
                "n_force": 1481, "n_images": 242}

    before, after = mis(454.85, 0.160), mis(337.17, 0.0)
    assert before["displacement_excess_px"] < MATERIAL_MIN * before["displacement_floor_px"]
    assert not is_material(before, after)
    why = not_material_text(before, after)
    assert "less than 30%" not in why
    assert why == ("the current model's error beyond the noise is already within 1.5 times its noise floor in the "
                   "displacement (0.16 against 0.122 px) and the force (0.0043 against 0.0196 N), as the model's own "
                   "mesh error leaves it with no hidden effect, and it lowers the chi2 by 0.49 per measurement (less "
                   "than 2)")
    # a channel with something to explain: the share it removed
    partial = not_material_text(mis(454.85, 0.5), mis(400.0, 0.4))
    assert "it removes 20% of the displacement's error beyond the noise (less than 30%)" in partial
    assert "already within" not in partial and partial.endswith("lowers the chi2 by 0.23 per measurement (less than 2)")
    # without the misfits (a session saved before): the rule alone
    assert not_material_text() == not_material_text({}, {})
    slide = Candidate("sliding-bottom", ("compressibility", "sliding-bottom"),
                      {"E_B_kPa": 17.97, "E_A_kPa": 61.5, "nu": 0.392}, {}, after, 1, 110.2, "slides", unmet=why)
    assert slide.explanation.endswith(f"(but {why}, so it is not a verdict)")
    assert Candidate.from_state(slide.state()).unmet == why
    base = Candidate("", ("compressibility",), {"E_B_kPa": 16.37, "E_A_kPa": 69.58, "nu": 0.456}, {}, before)
    d = Diagnosis("x", base, [slide], choose_verdict([slide]), NoiseModel(0.0196, 1481, 0.122, 242), 1.0)
    text = d.none_text()
    assert d.verdict == "none" and d.near_misses() == []
    assert "remove less than 30%" not in text
    assert text.startswith("No candidate is a finding: the current model's error beyond the noise is already within "
                           "1.5 times its noise floor (the displacement's 1.31 times, the force's 0.22 times)")
    assert "the best candidate, sliding-bottom (score +110), lowers it by 0.49" in text
    assert text.endswith("if the setup makes it plausible (specimen slides on the table), add it and compare the "
                         "versions")
    # a best candidate that fits no physical change is not offered
    neg = Candidate("compressibility", ("compressibility",), {"nu": 0.486}, {}, after, 1, 150.0, "", negligible="x")
    text = Diagnosis("x", base, [neg], "none", NoiseModel(0.0196, 1481, 0.122, 242), 1.0).none_text()
    assert "plausible" not in text and text.endswith("The best of them, compressibility (score +150), does not count: x")
    # with an error beyond 1.5 times its floor, no such sentence
    assert "already within" not in Diagnosis("x", Candidate("", (), {}, {}, mis(454.85, 0.3)), [slide], "none",
                                              NoiseModel(0.0196, 1481, 0.122, 242), 1.0).none_text()


def test_a_verdict_of_none_says_when_the_moduli_rest_on_an_effect_the_data_do_not_settle():
    """Blind paper seed 23029 (bench/paper_effects.py --cases lowres-slide
    --seed-offset 22000, diagnosed again 2026-11-30): a sliding bottom seen
    through 128 x 100 pixel images (26 x 20 mm, 76 mm above the table). The
    baseline is at the noise with E_A 21% low (49.7 kPa for 63); sliding-bottom
    lowers the chi2 by only 2.4 (score -5.0: less than its parameter's cost) and
    gives E_A 65.1. The verdict none must say that the moduli rest on the
    bottom being bonded, with the moduli the other model gives; a candidate that
    fits worse (probe-slip, E_A -10%), one that moves no modulus by 10% or a
    negligible one is not named."""
    from app.core.diagnose import UNRESOLVED_SHIFT, Candidate, Diagnosis, NoiseModel

    def mis(chi2):
        return {"chi2": chi2, "chi2_force": 1470.0, "chi2_images": chi2 - 1470.0, "force_rms_N": 0.0199,
                "displacement_rms_px": 0.3, "force_excess_N": 0.001, "force_floor_N": 0.0195,
                "displacement_excess_px": 0.0, "displacement_floor_px": 0.09, "n_force": 1481, "n_images": 18}

    base = Candidate("", (), {"E_B_kPa": 17.306, "E_A_kPa": 49.737}, {}, mis(1488.88))
    slide = Candidate("sliding-bottom", ("sliding-bottom",), {"E_B_kPa": 17.783, "E_A_kPa": 65.106}, {},
                      mis(1486.5), 1, -5.0, "slides")
    nu = Candidate("compressibility", ("compressibility",), {"E_B_kPa": 17.346, "E_A_kPa": 49.403, "nu": 0.489},
                   {}, mis(1489.0), 1, -7.4, "", negligible="a Poisson's ratio within 0.02 of the model's")
    slip = Candidate("probe-slip", ("probe-slip",), {"E_B_kPa": 17.614, "E_A_kPa": 44.57}, {}, mis(1495.5), 1,
                     -13.9, "slips")
    visco = Candidate("viscoelastic", ("viscoelastic",), {"E_B_kPa": 17.306, "E_A_kPa": 49.737, "g1": 0.0,
                                                          "tau1_s": 1000.0}, {}, mis(1488.88), 2, -14.6, "")
    d = Diagnosis("x", base, [slide, nu, slip, visco], "none", NoiseModel(0.0195, 1481, 0.25, 18), 1.0)
    assert abs(44.57 / 49.737 - 1) > UNRESOLVED_SHIFT  # the slip moves A, but fits worse
    assert [(c.effect, [n for n, _, _ in m]) for c, m in d.unresolved()] == [("sliding-bottom", ["A"])]
    text = d.none_text()
    assert text.startswith("No candidate effect lowers the misfit by more than its parameters cost"), text
    assert text.endswith(". The moduli rest on an assumption these measurements do not settle: with "
                         "sliding-bottom, which fits them at least as well (score -5, chi2 1,486.5 against 1,488.9), E_A "
                         "would be 31% higher (65.1 against 49.7 kPa) in the fits to the tracked blocks. If the setup allows it (specimen slides on the table), "
                         "add it and compare the versions"), text
    assert d.to_json_dict()["unresolved"] == [{"effect": "sliding-bottom", "moduli_kPa": {"E_A_kPa": 65.11}}]
    # a located sphere is placed where the misfit is: the moduli it moves are not an assumption of the setup
    incl = Candidate("inclusion", ("inclusion",), {"E_B_kPa": 17.3, "E_A_kPa": 40.0, "E_I_kPa": 90.0}, {},
                     mis(1482.4), 4, -24.8, "a region", reference=mis(1488.88))
    assert "inclusion" not in Diagnosis("x", base, [incl, slide], "none", NoiseModel(0.0195, 1481, 0.25, 18),
                                        1.0).none_text()
    # two: both named, and the advice for one of them
    slip2 = Candidate("probe-slip", ("probe-slip",), {"E_B_kPa": 15.2, "E_A_kPa": 49.9}, {}, mis(1487.9), 1, -6.4,
                      "slips")
    two = Diagnosis("x", base, [slide, slip2], "none", NoiseModel(0.0195, 1481, 0.25, 18), 1.0).none_text()
    assert ("assumptions these measurements do not settle: with sliding-bottom, which fits them at least as well (score -5, "
            "chi2 1,486.5 against 1,488.9), E_A would be 31% higher (65.1 against 49.7 kPa) in the fits to the tracked blocks; with probe-slip, which fits them at "
            "least as well (score -6, chi2 1,487.9 against 1,488.9), E_B would be 12% lower (15.2 against 17.3 kPa) in the fits to the tracked blocks. If the setup allows "
            "one of them (specimen slides on the table; probe slides on the surface), add that effect") in two, two
    # moduli within 10%, or a verdict: nothing to say
    near = Candidate("sliding-bottom", ("sliding-bottom",), {"E_B_kPa": 17.9, "E_A_kPa": 54.0}, {}, mis(1486.5), 1,
                     -5.0, "slides")
    assert Diagnosis("x", base, [near, nu], "none", NoiseModel(0.0195, 1481, 0.25, 18), 1.0).unresolved() == []
    found = Diagnosis("x", base, [slide, nu], "sliding-bottom", NoiseModel(0.0195, 1481, 0.25, 18), 1.0)
    assert found.unresolved() == [] and found.to_json_dict()["unresolved"] == []
    # added as the sentence advises, the version's note leaves it to the setup instead of saying "revert"
    from app.core.diagnose import support_warning

    assert support_warning(d, slide, 0) == (
        "sliding-bottom is no finding (score -5.0), but the measurements fit it at least as well as version 0, and "
        "it moves E_A to 65.1 kPa (from 49.7): keep it if the setup allows it (specimen slides on the table); else "
        "revert to version 0")
    assert "the data do not show it" in support_warning(d, slip, 0)  # it fits worse


def test_a_boundary_effect_that_hides_an_inclusion_is_named_with_a_none_verdict():
    """Blind paper seed 21004 (a probe slip and a 70 kPa sphere hidden together;
    docs/model-check.md): the slip alone fitted worse than the bonded model (chi2
    2,777 against 2,358, score -427), the inclusion alone was placed as the
    truth's mirror image, and the verdict was none. Scanned on the slipping model,
    the misfit pointed to a stiffer sphere at the truth's place explaining 990:
    the pair's estimate 1,787 against 2,046 for the best single candidate, a
    margin of 259, 6.8 times the pair's 5 parameters' cost (ln N = 7.6). On the
    sixteen paper phantoms with a verdict of none the margins were at most -2
    (probe-slip) and -264 (sliding-bottom), and on the 14 with one sphere hidden
    and found at most +25: no pair named (the demo's below)."""
    from app.core.diagnose import (MASKED_MARGIN, Candidate, Diagnosis, NoiseModel, masked_pair, pair_screen,
                                   support_warning)

    ln_n = 7.6
    assert masked_pair(2046.5, {"probe-slip": (2777.0, 989.8), "sliding-bottom": (5738.0, 3270.7)}, ln_n) == \
        "probe-slip"
    # the demo: probe-slip 1,884 - 183 against 1,672 (margin -30), sliding-bottom 6,715 - 4,623 (-421)
    assert masked_pair(1672.0, {"probe-slip": (1884.0, 183.0), "sliding-bottom": (6715.0, 4623.0)}, ln_n) == ""
    # blind seed 21012 (the slip over a sphere to the right; the inclusion verdict its mirror image): probe-slip's
    # pair estimated at 1,808 against 1,876, a margin of 68 (the cost 5 ln N is 38); the wide block's single
    # sphere (nothing else hidden): 2,299 against 2,324, a margin of 25, no pair
    assert masked_pair(1876.4, {"probe-slip": (2196.4, 388.2), "sliding-bottom": (5000.0, 2424.1)}, ln_n) == \
        "probe-slip"
    assert masked_pair(2323.7, {"probe-slip": (6120.3, 3821.7), "sliding-bottom": (9000.0, 4240.6)}, ln_n) == ""
    # a margin must pay the pair's parameters (MASKED_MARGIN x 5 ln N), not merely be positive
    assert masked_pair(2000.0, {"probe-slip": (2000.0, 5 * ln_n * MASKED_MARGIN - 1.0)}, ln_n) == ""
    assert masked_pair(2000.0, {"probe-slip": (2000.0, 5 * ln_n * MASKED_MARGIN + 1.0)}, ln_n) == "probe-slip"
    # the screen's figures, whether or not it names a pair (kept in the JSON and the session)
    screen = pair_screen(1672.0, {"probe-slip": (1884.0, 183.0), "sliding-bottom": (6715.0, 4623.0)}, ln_n)
    assert [s["effect"] for s in screen] == ["probe-slip", "sliding-bottom"]
    assert screen[0]["estimated_chi2"] == pytest.approx(1701.0) and screen[0]["margin"] == pytest.approx(-29.0)
    assert screen[1]["margin"] == pytest.approx(-420.0)
    assert all(s["needed"] == pytest.approx(MASKED_MARGIN * 5 * ln_n) for s in screen)

    def mis(chi2):
        return {"chi2": chi2, "force_rms_N": 0.02, "displacement_rms_px": 0.55, "force_excess_N": 0.004,
                "force_floor_N": 0.02, "displacement_excess_px": 0.4, "displacement_floor_px": 0.143}

    base = Candidate("", (), {"E_B_kPa": 17.9, "E_A_kPa": 67.5}, {}, mis(2358.0))
    slip = Candidate("probe-slip", ("probe-slip",), {"E_B_kPa": 18.2, "E_A_kPa": 59.5}, {}, mis(2777.0), 1, -426.7,
                     "slides")
    masked = {"effect": "probe-slip", "inclusion": {"name": "I", "center_mm": [57.5, 45.0, 85.2], "radius_mm": 5.4},
              "stiffer": True, "estimated_chi2": 1787.2, "best_single_chi2": 2046.5}
    noise = NoiseModel(0.02, 1481, 0.143, 242)
    d = Diagnosis("x", base, [slip], "none", noise, 1.0, masked=masked)
    text = d.none_text()
    assert text.startswith("No candidate effect lowers the misfit by more than its parameters cost")
    assert ("Or probe-slip and an undescribed inclusion hide each other: alone, probe-slip does not fit better "
            "(score -427), yet with it in the model the misfit points to a stiffer region at (57.5, 45.0, 85.2) mm, "
            "radius 5.4 mm") in text
    assert "chi2 1,787 against 2,046" in text and text.endswith("the next diagnosis names it")
    assert d.to_json_dict()["masked_pair"] == masked
    assert Diagnosis.from_state(d.state()).masked == masked
    d.masked_screen = [{"effect": "probe-slip", "estimated_chi2": 1787.2, "margin": 259.3, "needed": 76.0}]
    assert d.to_json_dict()["masked_screen"] == d.masked_screen
    assert Diagnosis.from_state(d.state()).masked_screen == d.masked_screen
    assert Diagnosis("x", base, [slip], "none", noise, 1.0).to_json_dict()["masked_screen"] is None
    # adding the slip it names: the version's note says why it fits worse, and what to do
    warn = support_warning(d, slip, 0)
    assert warn.startswith("probe-slip alone does not fit better than version 0 (score -427), as the diagnosis "
                           "expected") and "Diagnose again" in warn
    # without the masked pair: the usual warning
    assert "revert to version 0" in support_warning(Diagnosis("x", base, [slip], "none", noise, 1.0), slip, 0)
    assert Diagnosis("x", base, [slip], "none", noise, 1.0).masked_text() == ""
    # blind seed 21009 (the slip over a sphere further left): the verdict was an inclusion 11.3 mm off, at the
    # probe's corner (chi2 2,181), and with it added nothing more was found; scanned on the slipping model the
    # misfit pointed to a sphere 3.4 mm from the truth, the pair estimated at 1,850 (margin 331)
    assert masked_pair(2181.2, {"probe-slip": (3085.0, 1234.9), "sliding-bottom": (6397.0, 3700.0)}, ln_n) == \
        "probe-slip"
    incl = Candidate("inclusion", ("inclusion",), {}, {}, mis(2181.2), 4, 471.2, "a stiffer region", material=True)
    m9 = {**masked, "inclusion": {"name": "I", "center_mm": [28.7, 45.0, 85.2], "radius_mm": 5.4},
          "estimated_chi2": 1850.1, "best_single_chi2": 2181.2}
    d9 = Diagnosis("x", base, [incl, slip], "inclusion", noise, 1.0, masked=m9)
    assert d9.none_text() == ""
    assert d9.masked_text().startswith("probe-slip and the inclusion may hide each other: alone, probe-slip does not "
                                       "fit better (score -427)")
    assert "(the scan's estimate: chi2 1,850 against 2,181). Before adding the inclusion, add probe-slip" in \
        d9.masked_text()
    assert f"masked: {d9.masked_text()}" in d9.lines()
    # blind seed 21012: alone, the slip fitted better (+426) but was no finding (25% of the error beyond the noise)
    slip12 = Candidate("probe-slip", ("probe-slip",), {"E_B_kPa": 18.1, "E_A_kPa": 61.0}, {}, mis(2196.4), 1, 425.8,
                       "slides")
    d12 = Diagnosis("x", base, [incl, slip12], "inclusion", noise, 1.0, masked=m9)
    assert "alone, probe-slip fits better but is no finding (score +426), yet with it in the model" in \
        d12.masked_text(), d12.masked_text()
    assert support_warning(d12, slip12, 0).startswith("probe-slip alone fits better than version 0 but is no finding "
                                                      "(score +426), as the diagnosis expected")
    # blind seed 22202 (a sliding bottom and a slipping probe, no sphere): sliding-bottom was a finding
    # alone (+701) but below a stiff stand-in sphere under the probe (+1,935), the verdict
    slide = Candidate("sliding-bottom", ("sliding-bottom",), {"E_B_kPa": 17.4, "E_A_kPa": 75.6}, {}, mis(1911.8), 1,
                      701.4, "slides", material=True)
    incl22 = Candidate("inclusion", ("inclusion",), {}, {}, mis(1911.8), 4, 1935.4, "a stiffer region", material=True)
    m22 = {"effect": "sliding-bottom", "inclusion": {"name": "I", "center_mm": [39.5, 45.0, 88.8], "radius_mm": 6.4},
           "stiffer": False, "estimated_chi2": 1758.1, "best_single_chi2": 1911.8}
    d22 = Diagnosis("x", base, [incl22, slide], "inclusion", noise, 1.0, masked=m22)
    assert ("alone, sliding-bottom fits better (score +701, a finding too, but below the inclusion's +1,935), yet "
            "with it in the model the misfit points to a softer region") in d22.masked_text(), d22.masked_text()
    # a finding that scored higher but lost the near tie (the pattern match or the joint fit)
    slide.score = 2000.0
    assert "(score +2,000, a finding too, but the inclusion (+1,935) won the near tie)" in d22.masked_text()
    from app.core.export import verdict_html
    from app.gui.models.modelcheck import verdict_parts

    # the window and the report show the masked pair as a paragraph of its own, its first word in bold
    parts = verdict_parts(d9)
    assert parts[2] == f"But {d9.masked_text()}." and "may hide" not in parts[1]
    assert "<br><br><b>But</b> probe-slip and the inclusion may hide each other" in verdict_html(parts)
    # after a verdict of none the pair's sentence starts "Or", on the why line's heels in the terminal
    head, rest, said, tie = verdict_parts(d)
    assert said.startswith("Or probe-slip and an undescribed inclusion hide each other") and said.endswith("names it.")
    assert "hide each other" not in rest and not tie and rest.startswith(". ")
    assert f"masked: {said}" in d.lines() and f"why: {d.none_text(with_masked=False)}" in d.lines()
    assert d.none_text() == d.none_text(with_masked=False) + d.masked_text()
    assert "<b>Or</b> probe-slip and" in verdict_html(verdict_parts(d))


def test_a_lower_poissons_ratio_hidden_by_a_sliding_bottom_is_fitted_with_it_and_named():
    """Numbers from blind pair 43002 (Poisson's ratio 0.42 and a sliding bottom
    hidden, finest truth; docs/model-check.md, "Poisson's ratio and a sliding
    bottom hide each other"). Alone, compressibility fitted 0.474, within 0.02 of
    the model's 0.49 (no finding), the sliding bottom made the fit worse (-4,980)
    and the verdict was probe-slip (+632), with the moduli 11-12% off. The
    current model's displacement error was 4.06 times its floor, so the screen
    applies; fitted together, nu 0.4125 and a score of +899 against +766 for the
    best single effect (margin 132.5, 2 ln N = 14.9 needed), neither yielding:
    compressibility is the verdict, and its evidence says the sliding bottom
    comes next."""
    from app.core.diagnose import (RATIO_MASKED_MARGIN, RATIO_PAIR_RMS_MAX, Candidate, Diagnosis, NoiseModel,
                                   choose_verdict, name_masked_ratio, ratio_masked, ratio_screen_applies)

    def mis(chi2, excess_px):
        return {"chi2": chi2, "force_rms_N": 0.0198, "displacement_rms_px": 0.6, "force_excess_N": 0.0,
                "force_floor_N": 0.0209, "displacement_excess_px": excess_px, "displacement_floor_px": 0.1136}

    neg = "a Poisson's ratio within 0.02 of the model's is no finding: the mesh error alone moves the fit that far"

    def cands():
        comp = Candidate("compressibility", ("compressibility",), {"E_B_kPa": 16.23, "E_A_kPa": 69.93, "nu": 0.474},
                         {}, mis(1766.9, 0.222), 1, 766.5, "the tissue changes volume", negligible=neg)
        slip = Candidate("probe-slip", ("probe-slip",), {"E_B_kPa": 15.94, "E_A_kPa": 70.79}, {}, mis(1901.2, 0.300),
                         1, 632.2, "slides", material=True)
        slide = Candidate("sliding-bottom", ("sliding-bottom",), {"E_B_kPa": 16.13, "E_A_kPa": 113.6}, {},
                          mis(7513.7, 1.852), 1, -4980.4, "slides at the bottom")
        return [comp, slip, slide]

    base = Candidate("", (), {"E_B_kPa": 16.0, "E_A_kPa": 84.0}, {}, mis(2540.8, 0.461))
    out = cands()
    verdict = choose_verdict(out)
    assert verdict == "probe-slip"  # what the first diagnosis said before the screen
    assert ratio_screen_applies(out, base, 0.49, verdict)
    # not where the current model's error is within MATERIAL_MIN (1.5) times its floor: nothing to explain there
    assert not ratio_screen_applies(out, Candidate("", (), {}, {}, mis(2000.0, 0.16)), 0.49, verdict)
    assert ratio_screen_applies(out, Candidate("", (), {}, {}, mis(2000.0, 0.18)), 0.49, verdict)
    # the ratio may have moved up (blind pair 43005, nu 0.45 hidden with the sliding bottom: 0.495 alone)
    up = cands()
    up[0].parameters["nu"] = 0.495
    assert ratio_screen_applies(up, base, 0.49, verdict)
    # not when it is a finding by itself, or when either effect is the verdict
    found = cands()
    found[0].negligible = ""
    assert not ratio_screen_applies(found, base, 0.49, verdict)
    assert not ratio_screen_applies(out, base, 0.49, "compressibility")
    assert not ratio_screen_applies(out, base, 0.49, "sliding-bottom")

    ln_n = 7.448
    both = {"compressibility": "", "sliding-bottom": ""}
    fell = 0.276 / 0.629  # 43002's pair lowered the displacement RMS to 0.276 px from the current model's 0.629
    named, margin, needed = ratio_masked(899.0, 766.5, 2, ln_n, 0.4125, 0.49, both, fell)
    assert named and margin == pytest.approx(132.5) and needed == pytest.approx(RATIO_MASKED_MARGIN * 2 * ln_n)
    # the pair must pay for its parameters over the best single effect, its ratio must count, and neither may yield
    assert not ratio_masked(766.5 + needed - 1.0, 766.5, 2, ln_n, 0.4125, 0.49, both, fell)[0]
    assert ratio_masked(766.5 + needed + 1.0, 766.5, 2, ln_n, 0.4125, 0.49, both, fell)[0]
    assert not ratio_masked(899.0, 766.5, 2, ln_n, 0.475, 0.49, both, fell)[0]
    assert not ratio_masked(899.0, 766.5, 2, ln_n, 0.4125, 0.49,
                            {"compressibility": "", "sliding-bottom": "sliding-bottom raises chi2"}, fell)[0]
    # and it must lower the displacement error: face-slip+52000 with the slip added (nothing else hidden) fitted a
    # pair of nu 0.415 with a margin of 138.3 over the inclusion's +38.1, but its displacement RMS rose to 0.518 px
    # from 0.489, a false compressibility
    assert not ratio_masked(176.4, 38.1, 2, ln_n, 0.4149, 0.49, both, 0.518 / 0.489)[0]
    assert not ratio_masked(899.0, 766.5, 2, ln_n, 0.4125, 0.49, both, RATIO_PAIR_RMS_MAX + 0.01)[0]
    assert ratio_masked(899.0, 766.5, 2, ln_n, 0.4125, 0.49, both, RATIO_PAIR_RMS_MAX)[0]

    screen = {"effect": "sliding-bottom", "named": True, "nu": 0.4125,
              "parameters": {"E_B_kPa": 17.9802, "E_A_kPa": 61.8478, "nu": 0.4125}, "chi2": 1626.9, "score": 899.0,
              "best_single": "compressibility", "best_single_score": 766.5, "margin": 132.5, "needed": 14.9,
              "yields": both, "displacement_rms_px": 0.2805}
    assert name_masked_ratio(out, screen) == "compressibility"
    comp = out[0]
    assert comp.material and not comp.negligible and "not a verdict" not in comp.explanation
    assert ("fitted together with a sliding bottom it comes out at 0.41, and the pair explains more than any one "
            "effect (score +899 against +766 for compressibility; the displacement misfit 0.28 px; moduli B 17.98, "
            "A 61.85 kPa)") in comp.evidence
    assert comp.evidence.endswith("with it in the model the sliding bottom should be named next")
    d = Diagnosis("x", base, out, "compressibility", NoiseModel(0.0209, 1481, 0.1136, 236), 1.0, masked_ratio=screen)
    # probe-slip is within the near tie of compressibility alone, but the pair decided: no tie advice
    assert d.rival == "" and d.tie_advice() == ""
    assert d.to_json_dict()["masked_ratio"] == screen
    assert Diagnosis.from_state(d.state()).masked_ratio == screen
    # the next diagnosis, compressibility added (43005: nu 0.496, the error 1.32 times its floor): the sliding bottom
    # earned its parameters (+84) with nu 0.444, a finding though the error is that close to the noise
    from app.core.diagnose import unmasked_ratio_text, unmasks_ratio

    now = {"E_B_kPa": 15.85, "E_A_kPa": 72.55, "nu": 0.496}
    assert unmasks_ratio("sliding-bottom", ("compressibility",), now, {"E_B_kPa": 17.95, "nu": 0.4435})
    assert not unmasks_ratio("sliding-bottom", ("compressibility",), now, {"nu": 0.480})  # within 0.02
    assert not unmasks_ratio("probe-slip", ("compressibility",), now, {"nu": 0.4435})
    assert not unmasks_ratio("sliding-bottom", (), {"E_B_kPa": 15.85}, {"E_B_kPa": 17.95})
    assert unmasked_ratio_text(now, {"nu": 0.4435}).startswith(
        "with it Poisson's ratio moves from 0.496 to 0.444, further than the mesh alone moves it")
    # on a model with compressibility the sliding bottom is fitted from lower ratios too (43007: from the current
    # nu 0.499 alone it stopped at 0.479, where the pair had fitted 0.435); without it, from the current optimum
    from app.core.diagnose import _starts

    assert [x["nu"] for x in _starts("sliding-bottom", None, {"E_B_kPa": 17.1, "nu": 0.499})] == [0.499, 0.45, 0.40]
    assert _starts("sliding-bottom", None, {"E_B_kPa": 17.1}) == [{"E_B_kPa": 17.1}]
    # confirmed on the finer mesh by the same pair (43005: the pair there +1,105, nu 0.450), said so
    from dataclasses import replace

    conf = {"effects": ["compressibility"], "verdict": "compressibility", "confirmed": True, "scale": 0.7,
            "nodes": [3025, 7701], "ratio": 2.56, "excess_px": 0.428, "floor_px": 0.091,
            "candidates": {"compressibility": {"score": 965.8, "material": True, "explained": 0.5, "unmet": ""}},
            "masked_ratio": {**screen, "nu": 0.45, "score": 1105.3}, "seconds": 73.0}
    thin_base = replace(base, misfit=mis(2540.8, 0.233))
    c = Diagnosis("x", thin_base, out, "compressibility", NoiseModel(0.0209, 1481, 0.1136, 236), 1.0,
                  confirmation=conf, masked_ratio=screen).confirmation_text()
    assert c.endswith("compressibility is still a finding (score +966), fitted with the sliding bottom as here "
                      "(Poisson's ratio 0.45 with it; the pair's score +1,105): it is not the mesh's"), c
    # without the screen's figures the same candidates make a near tie with the slip
    assert Diagnosis("x", base, out, "compressibility", NoiseModel(0.0209, 1481, 0.1136, 236), 1.0).rival == \
        "probe-slip"


def test_a_pair_that_raises_the_displacement_error_is_not_named(monkeypatch):
    """The masked-ratio screen on a model with a probe slip added, nothing else
    hidden (face-slip+52000, diagnosed with ``--effects probe-slip``; figures from
    its diagnosis): compressibility alone fitted nu 0.486 (+19, no finding), and
    the pair with a sliding bottom scored +176 against the inclusion's +38, a
    margin of 138 where 14.9 is needed, neither yielding. Its chi2 was 191 lower,
    but its displacement RMS rose from 0.489 to 0.518 px, with E_B 12% high: the
    screen reports the pair but does not name it. The joint fit is stubbed; the
    screen's own arithmetic and the current model's RMS are what is tested."""
    import types

    import app.core.diagnose as dg

    ln_n = 7.3
    mis = {"chi2": 2862.4, "force_rms_N": 0.0195, "displacement_rms_px": 0.489}
    base = dg.Candidate("", ("probe-slip",), {"E_B_kPa": 17.98, "E_A_kPa": 63.06}, {}, mis)
    comp = dg.Candidate("compressibility", ("probe-slip", "compressibility"),
                        {"E_B_kPa": 17.91, "E_A_kPa": 63.60, "nu": 0.4864}, {}, {**mis, "chi2": 2836.0}, 1, 19.1,
                        negligible="within 0.02 of the model's")
    slide = dg.Candidate("sliding-bottom", ("probe-slip", "sliding-bottom"), {"E_B_kPa": 18.30, "E_A_kPa": 82.14},
                         {}, {**mis, "chi2": 6887.0}, 1, -4031.6)
    incl = dg.Candidate("inclusion", ("probe-slip", "inclusion"), {"E_B_kPa": 17.98, "E_I_kPa": 0.18}, {},
                        {**mis, "chi2": 2810.0}, 2, 38.1)

    def pair(rms):
        joint = dg.Candidate("compressibility+sliding-bottom", ("probe-slip", "compressibility", "sliding-bottom"),
                             {"E_B_kPa": 20.151, "E_A_kPa": 57.389, "nu": 0.4149}, {},
                             {**mis, "chi2": 2671.1, "displacement_rms_px": rms}, 2)
        return types.SimpleNamespace(joint=joint, yields={"compressibility": "", "sliding-bottom": ""})

    problem = types.SimpleNamespace(nu=0.49)
    noise = types.SimpleNamespace(n=int(round(math.exp(ln_n))))
    for rms, named in ((0.518, False), (0.276, True)):
        monkeypatch.setattr(dg, "_fit_pair", lambda *a, rms=rms, **k: pair(rms))
        said = []
        screen = dg._masked_ratio([incl, comp, slide], base, problem, None, noise, ln_n, 50, said.append, None)
        assert screen["named"] is named, screen
        assert screen["score"] == pytest.approx(2862.4 - 2671.1 - 2 * ln_n, abs=0.1)
        assert screen["best_single"] == "inclusion" and screen["margin"] > screen["needed"]
        assert screen["current_displacement_rms_px"] == 0.489 and screen["displacement_rms_px"] == rms
        assert f"displacement misfit 0.489 -> {rms:.3f} px" in said[-1]


def test_history_is_immutable_and_round_trips():
    h = ModelHistory()
    h1 = h.with_version((), {"E_B_kPa": 10.0}, {"total": -1.0}, {"force_rms_N": 0.3, "displacement_rms_px": 1.0})
    h2 = h1.with_version(("viscoelastic",), {"E_B_kPa": 12.0, "g1": 0.3}, {"total": -1.1},
                         {"force_rms_N": 0.02, "displacement_rms_px": 1.0})
    assert len(h) == 0 and len(h1) == 1 and len(h2) == 2
    assert h2.current == 1 and h2.reverted(0).current == 0 and len(h2.reverted(0)) == 2
    c = h2.compare(0, 1)
    assert c["added"] == ["viscoelastic"] and c["errors"]["force_rms_N"][2] == pytest.approx(0.02 / 0.3)
    assert ModelHistory.from_json_dict(h2.to_json_dict()) == h2
    with pytest.raises(IndexError):
        h2.reverted(5)
    # a version's mesh check is kept with it, through JSON; the others and the current one unchanged
    lines = ("version 0 (baseline)", "mesh check: on a mesh 0.7 times the size: E_B 10.0 -> 10.3 kPa (+3.0%)")
    h3 = h2.with_mesh_check(0, lines)
    assert h3.versions[0].mesh_check == lines and h3.versions[1] == h2.versions[1] and h3.current == 1
    assert h2.versions[0].mesh_check == () and h3.versions[0].parameters == h2.versions[0].parameters
    assert ModelHistory.from_json_dict(json.loads(json.dumps(h3.to_json_dict()))) == h3
    old = h3.to_json_dict()
    for v in old["versions"]:  # a session file saved before versions kept their mesh check
        del v["mesh_check"]
    assert ModelHistory.from_json_dict(old) == h2
    with pytest.raises(IndexError):
        h2.with_mesh_check(2, lines)


def test_diagnose_stops_when_cancelled(visco):
    exp, _ = visco
    cancel = threading.Event()
    cancel.set()
    from app.core.errors import Cancelled

    with pytest.raises(Cancelled):
        diagnose(exp, candidates=FAST, mesh_settings=ID_MESH, cancel=cancel)


IMAGE_CANDIDATES = ("sliding-bottom", "probe-slip", "compressibility", "viscoelastic")
# (effect, moduli tolerance {region: relative} with the effect added); the truths
# are synthetic.DIAGNOSE_CASES[effect] (sliding-bottom seed 13, probe-slip seeds 14 and 15,
# Poisson's ratio 0.3 seed 14).
# Measured with bench/diagnose_effects.py (IMG=192x180, fresh meshes each run,
# on the simulator before its echo phase was fixed):
# with sliding-bottom added E_B came within 3% in 7 of 7 runs and E_A within 8%
# in 6 of 7 (+17% in one: once the bottom slides, the field barely depends on
# the 7 mm inclusion, and mesh-to-mesh differences move it), so E_A holds 20%.
# The "e-" cases are the soft ellipsoid phantom (synthetic.DIAGNOSE_ELLIPSOID; sliding-bottom
# seed 22, Poisson's ratio 0.3 seed 24). Its probe slip (seed 23) leaves less in the images than
# the noise and the mesh error, so it is measured (bench/probe_slip_signal.py, docs/model-check.md
# "Hidden effects, measured"), not tested.
IMAGE_CASES = [("sliding-bottom", "sliding-bottom", {"B": 0.10, "A": 0.20}),
               ("probe-slip", "probe-slip", {"B": 0.10, "A": 0.10}),
               ("probe-slip-15", "probe-slip", {"B": 0.10, "A": 0.10}),
               ("compressibility", "compressibility", {"B": 0.10, "A": 0.10, "nu": 0.08}),
               ("compressibility-45", "compressibility", {"B": 0.10, "A": 0.10, "nu": 0.02}),
               ("e-sliding-bottom", "sliding-bottom", {"B": 0.10, "A": 0.20}),
               ("e-compressibility", "compressibility", {"B": 0.10, "A": 0.10, "nu": 0.08})]


@pytest.mark.parametrize("case,effect,tol", IMAGE_CASES, ids=[c[0] for c in IMAGE_CASES])
def test_hidden_image_effect_is_named_and_adding_it_fixes_the_moduli(tmp_path_factory, monkeypatch, case, effect,
                                                                     tol):
    """The truth has an effect the baseline lacks and that shows in the images
    (the specimen slides on the table, the probe slides on the surface, the
    tissue is compressible). The baseline's misfit has the pattern the effect
    predicts; the diagnosis names it first; with it the moduli come within
    tolerance (the baseline's were off by 10-200% on these cases) and the
    displacement error (systematic misfit beyond the tracking noise) falls.

    Measured on these meshes (2026-11-25, probe face meshed along its outline;
    bench/diagnose_effects.py with IMG=192x180): probe-slip 7.7x, sliding-bottom
    6.9x, compressibility to the noise (4.4x, 5.0x and to the noise before the
    outline was meshed); the issue's 3x is asserted. On the soft ellipsoid
    (2026-11-26): sliding-bottom 14x (moduli -1.5%, +0.4%; the baseline's E_A
    was +241%), compressibility 10x (nu 0.300, moduli -1.3%, -5.2%). Probe slip,
    seed 15 (2026-11-26): 4.4x, moduli -2.0%, +0.6% (the baseline's E_A was -23%).
    A Poisson's ratio of 0.45 (seed 18, 2026-11-26): nu 0.444, 17x, moduli -0.2%,
    -7.0% (baseline -7%, -22%); the verdict needs nu at least 0.02 from the
    model's 0.49 (see compressibility.NU_NEGLIGIBLE). Since weak blocks are
    confirmed by a larger block (2026-11-29) the falls are 4.6-11.3x or to the
    noise (docs/model-check.md, "Weak blocks confirmed by a larger block").

    The first probe slip is taken as a finding on a thin margin (CONFIRM_BELOW
    raised; its current model's error is 3.29 times its floor): diagnosed again
    on a mesh 0.7 times the size (committed; not the truth's, which is cached
    under a key of its own), the real slip is borne out there and stays the
    verdict (2026-12-01: 3,315 vertices against 1,575; the current model's error
    0.336 px against a floor of 0.137; the slip scores +310 and removes all of
    it; 6 s)."""
    forced = case == "probe-slip"
    if forced:
        monkeypatch.setattr("app.core.diagnose.CONFIRM_BELOW", 1e3)
    exp = _make(tmp_path_factory, case)
    d = diagnose(exp, candidates=IMAGE_CANDIDATES, mesh_settings=ID_MESH)
    assert d.verdict == effect, d.lines()
    k = d.confirmation
    if forced:
        assert k["effects"] == [effect] and k["confirmed"] and k["verdict"] == effect, d.lines()
        assert k["nodes"][1] > 2 * k["nodes"][0] and k["candidates"][effect]["material"], k
        assert next(x for x in d.lines() if x.startswith("confirmed: ")).endswith("it is not the mesh's"), d.lines()
    else:
        assert k is None, d.lines()
    c = d.candidate(effect)
    assert c.material and c.signature >= 0.6, d.lines()
    truth = read_truth(exp.path)
    for region, err in _moduli_errors(c.parameters, truth["moduli_kPa"]).items():
        assert abs(err) < tol[region], (region, err, d.lines())
    assert c.misfit["displacement_excess_px"] < d.baseline.misfit["displacement_excess_px"] / 3.0, d.lines()
    if effect == "compressibility":
        assert c.parameters["nu"] == pytest.approx(truth["nu"], abs=tol["nu"])
    if effect in ("probe-slip", "compressibility"):
        # forced into a near tie with the other one, the two fitted together still
        # say the truth's effect (2026-11-26: compressibility yielded on the slip
        # cases, by 0 and 5 of its cost of 7; probe-slip raised chi2 on the others)
        from dataclasses import replace

        from app.core.diagnose import _tie_break

        other = d.candidate("compressibility" if effect == "probe-slip" else "probe-slip")
        tied = [replace(x, score=100.0, material=True) for x in (other, c)]
        tb = _tie_break(tied, d.baseline.problem, d.tracked, d.noise, 200, lambda s: None, None)
        assert tb.winner == effect and tb.yields[other.effect] and not tb.yields[effect], (tb.to_json_dict(), d.lines())


@pytest.mark.parametrize("case,short_of_memory", [("inclusion", False), ("e-inclusion", True)])
def test_hidden_inclusion_is_located_and_adding_it_lowers_the_error(tmp_path_factory, monkeypatch, case,
                                                                    short_of_memory):
    """A 4 mm stiffer sphere the experiment does not describe, beside region A
    (seed 13: 60 kPa in 15 kPa tissue beside a stiff sphere; seed 25: 72 kPa in
    24 kPa tissue above the soft ellipsoid's edge). The sensitivity scan puts the
    new region near it (within 3 mm on seed 13), the diagnosis names it, the
    error beyond the noise falls, and the described moduli stay right.

    On seed 25 (committed meshes, 2026-11-29: the located sphere's mesh is committed
    too) the located sphere is 1.1 mm from the truth's: radius 4.8 mm at
    (33.1, 20, 25.4) against 4 mm at (32, 20, 25), fitted 2.0 times stiffer than
    its tissue (47 kPa in 23.4) where the truth is 3 times. The error beyond the
    noise falls from 0.330 px to within the noise, moduli -2.4% and -4.8%. Before
    the scan was scored by the Huber loss (inclusion.huber_fits) its sphere had
    radius 3.2 mm, fitted 7 times stiffer (the smaller sphere, the stiffer: size
    and stiffness trade off in the tracked field), moduli -2.3% and -3.9%; before
    weak blocks were confirmed by a larger block (compare.track) it was 5.4 mm
    away, at (36.3, 20, 28.3), 34 times stiffer.

    Seed 25 runs short of memory (ELASTOID_MEMORY_GB below what the process
    holds): the model with the sphere is then built in turn, after probe-slip,
    rather than beside it, and says so."""
    exp = _make(tmp_path_factory, case)
    truth = read_truth(exp.path)
    c_true = np.array(truth["hidden_regions"][0]["center_mm"], float)
    if short_of_memory:
        monkeypatch.setenv("ELASTOID_MEMORY_GB", "0.001")
        import app.core.diagnose as diagnose_module  # the placement's full search runs in the other case

        monkeypatch.setattr(diagnose_module, "PLACE_MAX_TRIALS", 2)
    said = []
    d = diagnose(exp, candidates=("inclusion", "probe-slip"), mesh_settings=ID_MESH, progress=said.append)
    deferred = [s for s in said if s.startswith("inclusion located at") and "memory is short" in s]
    assert len(deferred) == int(short_of_memory), said
    if short_of_memory:  # built after probe-slip was tried
        assert said.index(deferred[0]) < said.index("trying probe-slip") < said.index("trying inclusion"), said
    noted = [line for line in d.lines() if line.startswith("memory: memory was short")]  # the report says so too
    assert len(noted) == int(short_of_memory), d.lines()
    monkeypatch.delenv("ELASTOID_MEMORY_GB", raising=False)
    assert d.verdict == "inclusion", d.lines()
    # the probe does not slip here: the masked-pair screen (it runs with an inclusion verdict) names nothing
    assert d.masked is None and not any(line.startswith("masked:") for line in d.lines()), d.lines()
    assert [s["effect"] for s in d.masked_screen] == ["probe-slip"], d.masked_screen
    assert d.masked_screen[0]["margin"] <= d.masked_screen[0]["needed"], d.masked_screen
    c = d.candidate("inclusion")
    synthetic.assert_mesh_committed(exp, c.inclusion)  # the sphere's mesh too: the outcome depends on it
    assert np.linalg.norm(np.array(c.inclusion["center_mm"]) - c_true) < 3.0, c.inclusion
    assert c.parameters[f"E_{c.inclusion['name']}_kPa"] > c.parameters["E_B_kPa"], c.parameters  # stiffer
    hidden = {r["name"] for r in truth["hidden_regions"]}
    described = {k: v for k, v in truth["moduli_kPa"].items() if k not in hidden}
    for region, err in _moduli_errors(c.parameters, described).items():
        assert abs(err) < 0.10, (region, err, d.lines())
    # The located sphere (one of three radii, centre not refined) is meshed as a region; that mesh is
    # committed too (tests/data/meshes), since fTetWild is not deterministic. Measured on these meshes
    # (2026-11-25): the error beyond the noise falls 6.2x (0.319 -> 0.052 px; 5.9x since weak blocks are
    # confirmed by a larger block, 2026-11-29); the true sphere, given
    # as a described region, leaves 0.102 px (bench/inclusion_floor.py). Before the probe face was
    # meshed along its outline the same case fell 1.43x: the unbonded strip along the probe's edges,
    # different in the truth's mesh and the model's, left an error no inclusion could remove.
    assert c.misfit["displacement_excess_px"] < d.baseline.misfit["displacement_excess_px"] / 3.0, d.lines()
    # the identification then searches the sphere's place and radius by NMI and force (place_by_identification)
    ident = d.identified
    placed = ident.get("inclusion", c.inclusion)
    (hidden_name,) = hidden
    assert ident["place_trials"] > 1 and ident["effects"] == ["inclusion"], ident
    # the outline's size it rests on, and the advice when it is coarser than advised
    assert ident["outline_mm"] == (ID_MESH.outline_edge_mm or ID_MESH.probe_edge_mm), ident
    assert ("rests on the mesh along the probe face's outline" in d.identified_text()) == (ident["outline_mm"] > 1.0)
    assert np.linalg.norm(np.array(placed["center_mm"]) - c_true) < 3.0, placed
    # measured (2026-11-30, the full search in both cases): placed 0.8 and 1.1 mm from the hidden sphere
    # (located: 1.4 and 1.2 mm), E_I -6.5% and -14.9% of the truth's on these coarse test meshes; on the paper-size blind seeds -4.7% and -3.7%
    # (located: -16.4% and +27.4%), docs/model-check.md
    if "inclusion" in ident:  # moved: the identification's cost is lower there than at the located sphere
        assert ident["cost"]["total"] < ident["located_cost"]["total"], ident
        assert f"{placed['name']} centred at ({placed['center_mm'][0]:.1f}" in d.identified_text(), d.identified_text()
        # the spheres the frames do not tell from the placed one: every trial had its jackknife groups (the
        # test ROI holds enough blocks), and the hidden sphere's modulus lies in the range they give (measured
        # 2026-12-01 on the full search: all 9 trials within two standard errors, E_I 48.0-72.0 kPa); the line
        # says it when more than one trial is in it
        spread = ident["place_spread"]
        assert spread["of"] == ident["place_trials"], spread
        E_hidden = truth["moduli_kPa"][hidden_name]
        assert spread["E_kPa"][0] <= E_hidden <= spread["E_kPa"][1], (E_hidden, spread)
        assert ("trial spheres fit the frames as well" in d.identified_text()) == (spread["trials"] > 1), \
            d.identified_text()
    # forced into a near tie with probe-slip, the two are fitted together on the inclusion's mesh (the slip
    # fitted there too, without the sphere): the inclusion earns its parameters on top of the slip, and the
    # tie goes to the inclusion. Whether the slip yields is not asserted: it is a switch, with no parameter
    # that gives back the model without it, and on seed 25 it moved chi2 on top of the sphere by -4 to +12
    # over five fresh meshes of the located sphere (2026-11-29), about its cost (ln N, 7). One CI run, on
    # a fresh mesh of the sphere, found no single loser (its message was cut short; most likely the slip
    # lowered chi2 by more than its cost, and then the pattern match decides). The sphere's mesh is
    # committed since; on it the slip raises chi2 by 6.
    from dataclasses import replace

    from app.core.diagnose import _tie_break, choose_verdict

    tied = [replace(x, score=100.0, material=True) for x in (d.candidate("probe-slip"), c)]
    tb = _tie_break(tied, d.baseline.problem, d.tracked, d.noise, 200, lambda s: None, None)
    why = (tb.yields, tb.joint.parameters, tb.joint.misfit["chi2"], tb.beside_chi2)
    assert not tb.yields["inclusion"], why
    assert choose_verdict(tied, tb) == "inclusion", why
    assert tb.joint.parameters[f"E_{c.inclusion['name']}_kPa"] > tb.joint.parameters["E_B_kPa"], tb.joint.parameters


def test_the_placement_spread_holds_the_trials_the_frames_do_not_tell_apart():
    """_place_spread: a trial is kept beside the best when its cost exceeds the
    best's by at most two jackknife standard errors of the difference (over the
    same groups of blocks), and the inclusion's modulus is reported over them."""
    from app.core.diagnose import PLACE_SPREAD_SIGMAS, _place_spread

    rng = np.random.default_rng(1)
    base = rng.normal(size=16)

    def trial(r, E, cost, scatter):  # its cost with each group left out: the best's, shifted and scattered
        groups = base + (cost - 0.0) + scatter * rng.standard_normal(16)
        return {"sphere": {"radius_mm": r}, "E_kPa": E, "cost": cost, "groups": groups}

    best = {"sphere": {"radius_mm": 6.0}, "E_kPa": 6.0, "cost": 0.0, "groups": base.copy()}
    near = trial(7.5, 9.0, 0.01, 0.05)  # 0.01 above, the difference's standard error about 0.2: kept
    far = trial(9.5, 14.0, 0.01, 1e-4)  # as far above, but the groups agree on it: told apart
    unknown = {"sphere": {"radius_mm": 3.0}, "E_kPa": 1.0, "cost": 0.001, "groups": None}  # too few blocks
    spread = _place_spread([best, near, far, unknown], 6.5)
    assert PLACE_SPREAD_SIGMAS == 2.0
    assert spread == {"trials": 2, "of": 3, "E_kPa": [6.0, 9.0], "radius_mm": [6.0, 7.5]}, spread
    assert _place_spread([unknown], 1.0) is None and _place_spread([], 1.0) is None


def test_an_inclusion_verdict_whose_identified_modulus_goes_to_a_bound_is_no_finding(monkeypatch):
    """The verdict's model is identified as identify does, and the identification
    places the sphere. Where that takes the inclusion's modulus to a bound of the
    fit, the sphere stands for a pattern it cannot represent: the inclusion is no
    finding, the verdict goes to the next finding (or none), and that one's model
    is identified in turn. Blind phantom 42011 (a 40 kPa sphere on the right edge
    of the view): a softer sphere located left of the view, 9.9 kPa in the
    candidate's fit (+283), was placed further out by the identification with
    0.1 kPa, and had been the verdict."""
    import app.core.diagnose as dg
    import app.core.mesh_check as mesh_check
    from app.core.diagnose import Candidate, _identify_verdict, identified_at_bound

    class Model:  # the part of an EffectProblem the step uses
        def release(self, keep=None):
            pass

    sphere = {"name": "I", "center_mm": [21.5, 45.0, 90.1], "radius_mm": 5.4}
    placed = {"name": "I", "center_mm": [15.7, 45.0, 90.1], "radius_mm": 5.4}
    misfit = {"chi2": 1000.0, "displacement_excess_px": 0.2}

    def candidates():
        inc = Candidate("inclusion", ("inclusion",), {"E_B_kPa": 18.3, "E_A_kPa": 62.3, "E_I_kPa": 9.9}, {}, misfit,
                        4, 283.0, "a softer region", sphere, problem=Model(), material=True)
        slip = Candidate("probe-slip", ("probe-slip",), {"E_B_kPa": 18.0, "E_A_kPa": 63.0}, {}, misfit, 1, 200.0,
                         "the tissue slides", problem=Model(), material=True)
        return [inc, slip]

    identified = []

    def identify(problem, verdict, start, say, cancel):
        identified.append(verdict)
        if verdict == "inclusion":
            return {"parameters": {**start, "E_I_kPa": e_placed}, "cost": {"total": -1.0}, "seconds": 1.0,
                    "inclusion": placed}
        return {"parameters": dict(start), "cost": {"total": -1.0}, "seconds": 1.0}

    monkeypatch.setattr(dg, "_identified_verdict", identify)
    monkeypatch.setattr(mesh_check, "identification_settings", lambda *a: type("S", (), {"outline_mm": 1.0}))
    said = []
    base = Candidate("", (), {}, {}, misfit)
    # placed at the lower bound: the inclusion falls, and the slip is the verdict, identified in its turn
    out, e_placed = candidates(), 0.1
    assert _identify_verdict(out, "inclusion", None, None, base, None, None, None, said.append, None) == "probe-slip"
    assert identified == ["inclusion", "probe-slip"] and out[1].identified["parameters"]["E_B_kPa"] == 18.0
    inc = out[0]
    assert not inc.material and inc.identified["parameters"]["E_I_kPa"] == 0.1  # kept: the user may add it anyway
    assert inc.negligible == identified_at_bound(inc)
    assert inc.negligible.startswith("identified as elastoid identify does (NMI and force) and placed by it at "
                                     "(15.7, 45.0, 90.1) mm, radius 5.4 mm, its modulus went to the fit's lower "
                                     "bound (0.1 kPa: as soft as a fluid)"), inc.negligible
    assert f"inclusion: no finding ({inc.negligible})" in said
    assert inc.explanation.endswith(f"(but {inc.negligible}, so it is not a verdict)"), inc.explanation
    # with no other finding, none (the current model's identification is the diagnosis' own)
    identified.clear()
    out, e_placed = candidates(), 10000.0
    out[1].material = False
    assert _identify_verdict(out, "inclusion", None, None, base, None, None, None, said.append, None) == "none"
    assert identified == ["inclusion"] and "upper bound (10,000 kPa: a rigid body)" in out[0].negligible
    from app.core.diagnose import Diagnosis, NoiseModel

    why = Diagnosis("x", base, out, "none", NoiseModel(0.02, 1481, 0.12, 236), 1.0).none_text()
    assert why.endswith(f"The best of them, inclusion (score +283), does not count: {out[0].negligible}"), why
    # a modulus inside the bounds: the verdict stands, whether the sphere moved or not
    identified.clear()
    out, e_placed = candidates(), 14.0
    assert _identify_verdict(out, "inclusion", None, None, base, None, None, None, said.append, None) == "inclusion"
    assert identified == ["inclusion"] and out[0].material and not out[0].negligible
    assert identified_at_bound(Candidate("inclusion", (), {}, {}, {}, inclusion=sphere,
                                         identified={"parameters": {"E_I_kPa": 0.1}})).startswith(
        "identified as elastoid identify does (NMI and force) at (21.5, 45.0, 90.1) mm, radius 5.4 mm, its modulus")


@pytest.mark.parametrize("short_of_memory", [False, True])
def test_a_rival_place_is_meshed_and_fitted_too_and_the_better_fit_kept(tmp_path_factory, monkeypatch,
                                                                         short_of_memory):
    """When the scan reports a rival place, both spheres are meshed and fitted, and
    the candidate is the one that lowers chi2 more (each from the current model on
    its own mesh); its inclusion says what the other did. Every scan here gets a
    rival (RIVAL_SHARE 0: the best sphere that does not overlap the best). On seed
    13 the best is the hidden sphere's place (within 3 mm), and it fits better
    than the rival. Both spheres' meshes are committed (tests/data/meshes); what is
    asserted held on fresh meshes of the rival too. Short of memory, both models
    are built in turn (after the other candidates), and it says so."""
    import app.core.diagnose as diagnose_module
    from app.core.effects import inclusion as inclusion_effect

    monkeypatch.setattr(inclusion_effect, "RIVAL_SHARE", 0.0)
    monkeypatch.setattr(diagnose_module, "PLACE_MAX_TRIALS", 1)  # the identification's search: tested above
    exp = _make(tmp_path_factory, "inclusion")
    c_true = np.array(read_truth(exp.path)["hidden_regions"][0]["center_mm"], float)
    if short_of_memory:
        monkeypatch.setenv("ELASTOID_MEMORY_GB", "0.001")
    said = []
    d = diagnose(exp, candidates=("inclusion",), mesh_settings=ID_MESH, progress=said.append)
    monkeypatch.delenv("ELASTOID_MEMORY_GB", raising=False)
    located = [s for s in said if s.startswith("inclusion located at")]
    assert len(located) == 1 and "both are built and fitted" in located[0], said
    assert ("their models are built after the other candidates" in located[0]) == short_of_memory, located
    assert any(s.startswith("fitting the inclusion at the rival place") for s in said), said
    c = d.candidate("inclusion")
    inc = c.inclusion
    assert np.linalg.norm(np.array(inc["center_mm"]) - c_true) < 3.0, inc
    assert ("also_fits" in inc) != ("rival_fitted" in inc), inc
    other = inc.get("also_fits") or inc["rival_fitted"]
    assert other["fitted"] and other["explained"] <= other["explained_here"], inc
    assert math.dist(other["center_mm"], inc["center_mm"]) > other["radius_mm"] + inc["radius_mm"], inc
    # both spheres' meshes are committed: fTetWild is not deterministic, and a fresh mesh of the rival
    # once ran past the 600 s test timeout in CI (2026-11-29), where it had taken seconds here
    for place in (inc, {**other, "name": inc["name"]}):
        synthetic.assert_mesh_committed(exp, place)
    # the kept gain is the candidate's: its score plus the four parameters' cost
    assert abs(c.score + c.n_parameters * math.log(d.noise.n) - other["explained_here"]) < 0.1, (c.score, inc)
    # the model kept is the kept place's
    assert c.problem is not None and c.problem.inclusion["center_mm"] == inc["center_mm"]
    assert "meshed and fitted too" in c.evidence, c.evidence
    assert d.verdict == "inclusion", d.lines()


def test_locating_an_inclusion_for_identify_fits_a_rival_place_too(tmp_path_factory, monkeypatch):
    """`elastoid identify --effects inclusion` places the sphere by the same steps
    as the diagnosis' candidate, the rival place included: both meshed and fitted,
    the better kept. Every scan gets a rival here (RIVAL_SHARE 0); on seed 13 the
    kept place is the hidden sphere's (within 3 mm)."""
    from app.core.diagnose import locate_inclusion
    from app.core.effects import inclusion as inclusion_effect

    monkeypatch.setattr(inclusion_effect, "RIVAL_SHARE", 0.0)
    exp = _make(tmp_path_factory, "inclusion")
    c_true = np.array(read_truth(exp.path)["hidden_regions"][0]["center_mm"], float)
    said = []
    inc = locate_inclusion(exp, ("inclusion",), mesh_settings=ID_MESH, progress=said.append)
    assert any(s.startswith("fitting the inclusion at the rival place") for s in said), said
    assert np.linalg.norm(np.array(inc["center_mm"]) - c_true) < 3.0, inc
    other = inc.get("also_fits") or inc["rival_fitted"]
    assert other["fitted"] and other["explained"] <= other["explained_here"], inc
    assert set(inc) - {"also_fits", "rival_fitted"} == {"name", "center_mm", "radius_mm"}, inc
    for place in (inc, {**other, "name": inc["name"]}):  # the meshes the outcome depends on, committed
        synthetic.assert_mesh_committed(exp, place)


def test_refining_an_inclusion_moves_it_to_where_the_data_put_it(tmp_path_factory):
    """The hidden 4 mm sphere of seed 13 (60 kPa at (26, 20, 14) mm in 15 kPa
    tissue beside region A), given 3 mm off to the side as the model's inclusion:
    refining (ModelCheck.refine_inclusion, every trial on that model's mesh)
    walks it back. Measured on the committed meshes (2026-11-29): 13 trials, the
    best at (25.4, 20, 14) mm, radius 4, 0.6 mm from the truth (error beyond the
    noise 0.160 -> 0.058 px on the first mesh); meshed there, the new version's
    error is within the noise (0.168 px before), chi2 975 -> 760, moduli B
    14.8, A 43.2 (15, 45), the sphere 67 kPa. 45 s here."""
    from app.core.diagnose import ModelCheck

    exp = _make(tmp_path_factory, "inclusion")
    truth = read_truth(exp.path)
    c_true = np.array(truth["hidden_regions"][0]["center_mm"], float)
    off = {"name": "I", "center_mm": [c_true[0] + 3.0, c_true[1], c_true[2]], "radius_mm": 4.0}
    synthetic.assert_mesh_committed(exp, off)
    mc = ModelCheck(exp, mesh_settings=ID_MESH)
    mc.identify(())
    with pytest.raises(ElastoidError, match="has no inclusion to refine"):
        mc.refine_inclusion()
    v1 = mc.identify(("inclusion",), inclusion=off)
    mesh1 = mc.problem.mesh
    said = []
    v2 = mc.refine_inclusion(progress=said.append)
    synthetic.assert_mesh_committed(exp, v2.inclusion)
    assert v2.index == v1.index + 1 and v2.note == "refined the inclusion's place" and not v2.warning, v2
    assert sum(line.startswith("inclusion at") for line in said) >= 7, said  # trials reported as they go
    from app.core.effects.inclusion import inside_specimen

    assert all(inside_specimen(t.inclusion["center_mm"], t.inclusion["radius_mm"], exp.specimen.size_mm)
               for t in mc.last_search), [t.inclusion for t in mc.last_search]
    moved = np.linalg.norm(np.array(v2.inclusion["center_mm"]) - c_true)
    assert moved < 1.5, (v2.inclusion, said)
    assert mc.problem.mesh is not mesh1  # meshed at its new place, not the old mesh reused
    assert v2.misfit["chi2"] < v1.misfit["chi2"] - 100, (v1.misfit, v2.misfit)
    assert v2.misfit["displacement_excess_px"] < v1.misfit["displacement_excess_px"] / 3.0, (v1.misfit, v2.misfit)
    for region, err in _moduli_errors(v2.parameters, {"B": 15.0, "A": 45.0}).items():
        assert abs(err) < 0.10, (region, err, v2.parameters)


def test_a_refined_inclusion_warns_unless_its_new_mesh_keeps_most_of_the_gain_found():
    """The figures measured (2026-11-29): at paper size the search found chi2 396
    on the added version's mesh (2,270 -> 1,874) and the new mesh kept 293 of it
    (2,270 -> 1,977): no warning. On seed 13's test phantom, with the sphere the
    diagnosis located (1.3 mm off), the search found 23 and the new mesh lost 4:
    a warning. A run in the window kept a fall of 3 (826.5 -> 823.5; what its
    search found was not recorded): against a find of 40, that warns too."""
    from app.core.diagnose import refine_warning

    assert refine_warning(1, 2270.4, 1977.4, 2270.4 - 1874.5) == ""
    assert refine_warning(1, 975.0, 760.0, 962.7 - 783.3) == ""  # kept more than found
    worse = refine_warning(1, 782.8, 787.2, 782.8 - 760.1)
    assert "fits the measurements worse than version 1" in worse and "787 against 783" in worse, worse
    little = refine_warning(3, 826.5, 823.5, 40.0)
    assert little.startswith("meshed at its new place, the inclusion gains chi2 3 where the search found 40 on "
                             "version 3's mesh"), little
    assert "revert to version 3" in little, little
    assert refine_warning(3, 826.5, 806.5, 40.0) == ""  # half of it kept


def test_a_search_that_finds_less_than_a_mesh_moves_makes_no_version():
    """On the paper-size seed with its inclusion out of view (2026-11-29), the
    search's 16 trials found chi2 1,869.9 against the start's 1,873.1; meshed, that
    sphere fitted worse (1,940): a fall of 3 is under what a new mesh moves
    (1.3-5.8% of chi2 there). Refused, with the reason; so is seed 13's find of
    23 (2.9%, 782.8 -> 760.1), which meshed anew kept 13 and moved E_A from -3%
    to -9%; in view, the 396 found (2,270.4 -> 1,874.5) goes on."""
    from app.core.diagnose import InclusionTrial, refine_refusal

    def trials(*chi2):
        return [InclusionTrial({"name": "I", "center_mm": [21.5 - i, 45.0, 74.4], "radius_mm": 5.4}, c, {}, {})
                for i, c in enumerate(chi2)]

    why = refine_refusal(trials(1873.1, 1884.6, 1869.9, 1870.2))
    assert why.startswith("the inclusion already sits about where it fits best: the best of the 4 places"), why
    assert "(19.5, 45.0, 74.4) mm with radius 5.4 mm" in why and "chi2 3.2 better (of 1,873)" in why, why
    assert "already sits where it fits best among the 2" in refine_refusal(trials(1873.1, 1884.6))
    assert refine_refusal(trials(2270.4, 2171.6, 1874.5)) == ""
    assert "only by chi2 22.7 better (of 783)" in refine_refusal(trials(782.8, 760.1))
    assert refine_refusal(trials(782.8, 757.0)) == ""  # 3.3%


@pytest.mark.parametrize("outcome", ["refined", "worse", "little", "refused"])
def test_a_batch_keeps_the_located_inclusion_unless_the_refined_one_fits_better(monkeypatch, outcome):
    """refine_located_inclusion (identify --refine-inclusion) on the Model check's
    steps, stubbed here (they are tested on data above): the refined sphere is
    used only when its version has no warning, and the note says why not, in
    the batch's words (the located sphere, not a version number)."""
    import app.core.diagnose as dg

    located = {"name": "I", "center_mm": [24.7, 20.0, 13.8], "radius_mm": 4.5}
    moved = dict(located, center_mm=[25.3, 20.0, 14.4], radius_mm=3.9)
    identified = []

    def identify(self, effects=(), *, inclusion=None, **kw):
        identified.append((tuple(effects), inclusion))
        return dg.ModelVersion(len(identified) - 1, tuple(effects), {}, {}, {"chi2": 787.0}, inclusion=inclusion)

    def refine(self, **kw):
        self.last_search = [dg.InclusionTrial(located, 783.0, {}, {}), dg.InclusionTrial(moved, 760.0, {}, {})]
        if outcome == "refused":
            raise dg.RefinementRefused("the inclusion already sits about where it fits best")
        chi2 = {"refined": 774.0, "worse": 790.0, "little": 780.0}[outcome]
        warning = dg.refine_warning(1, 787.0, chi2, 23.0)
        return dg.ModelVersion(2, ("inclusion",), {}, {}, {"chi2": chi2}, inclusion=moved, warning=warning)

    monkeypatch.setattr(dg.ModelCheck, "identify", identify)
    monkeypatch.setattr(dg.ModelCheck, "refine_inclusion", refine)
    out = dg.refine_located_inclusion(None, ("inclusion", "hyperelastic"), located)
    assert identified == [((), None), (("inclusion",), located)]  # refined without the nonlinearity
    assert out["located"] == located and out["chi2_located"] == 787.0
    if outcome == "refined":
        assert out["refined"] and out["inclusion"] == moved and out["chi2_refined"] == 774.0
        assert out["note"] == "the refined sphere fits the measurements better than the located one (chi2 774 " \
                              "against 787)", out
        return
    assert not out["refined"] and out["inclusion"] == located, out
    assert out["note"].startswith("the located sphere is kept: "), out
    assert "version" not in out["note"], out
    words = {"worse": "fits the measurements worse than the located sphere on its own mesh (chi2 790 against 787)",
             "little": "gains chi2 7 where the search found 23 on the located sphere's mesh",
             "refused": "already sits about where it fits best"}[outcome]
    assert words in out["note"], out
    assert out["chi2_refined"] == (None if outcome == "refused" else {"worse": 790.0, "little": 780.0}[outcome])


def test_an_inclusion_keeps_inside_the_specimen():
    from app.core.effects.inclusion import WALL_GAP_MM, inside_specimen

    size = (90.0, 90.0, 96.0)
    assert inside_specimen([45, 45, 84], 6.0, size)
    assert inside_specimen([45, 45, 96 - 6.0 - WALL_GAP_MM], 6.0, size)  # at the gap exactly
    assert not inside_specimen([30.5, 45, 95.5], 4.7, size)  # into the probe's face (a blind seed's search did)
    assert not inside_specimen([3.0, 45, 50], 3.0, size) and not inside_specimen([45, 89.0, 50], 1.0, size)


def test_the_scan_tries_spheres_partly_out_of_view_and_no_wider_than_the_field_allows():
    """The paper-size field (tracked x 28.7-60.7 mm, z 63.6-92.4 mm in a 90 x 90 x 96
    mm block, steps of 3.6 mm): centres reach a radius beyond the field (the hidden
    sphere of seed 105 is centred at x = 22, outside it), the grid inside the field
    is the one scanned before, no sphere is wider than MAX_WIDTH of the field
    (the 13.5 mm radius is capped at 6.4), and every sphere lies inside the block."""
    from app.core.effects.inclusion import MAX_WIDTH, candidate_spheres, capping_width

    lo, hi, size, step = np.array([28.7, 45.0, 63.6]), np.array([60.7, 45.0, 92.4]), (90.0, 90.0, 96.0), 3.6
    sph = candidate_spheres(lo, hi, (45.0, 45.0, 0.0), (1.0, 0.0, 0.0), size, [5.4, 9.0, 13.5], step, 32.0)
    radii = sorted({r for _, r in sph})
    assert radii == [5.4, pytest.approx(0.5 * MAX_WIDTH * 32.0)] and max(radii) == pytest.approx(6.4)
    C = np.array([c for c, _ in sph])
    R = np.array([r for _, r in sph])
    assert np.all(C - R[:, None] >= 0.5 - 1e-9) and np.all(C + R[:, None] <= np.array(size) - 0.5 + 1e-9)
    assert C[:, 0].min() < lo[0] - 5.0 and C[:, 2].min() < lo[2] - 5.0  # beyond the field
    assert len({(tuple(np.round(c, 6)), r) for c, r in sph}) == len(sph)  # no repeats
    for x in np.arange(lo[0], hi[0] + 1e-9, step):  # the in-field grid of before, radius 5.4
        for z in np.arange(lo[2], hi[2] + 1e-9, step):
            c = np.clip([x, 45.0, z], 5.9, np.array(size) - 5.9)
            assert np.any((np.abs(C - c).max(axis=1) < 1e-9) & (R == 5.4)), c
    # a field the cap does not bind (the test phantoms': 29 mm wide, radii up to 4.5 mm)
    sph = candidate_spheres(np.array([5.5, 20, 4.2]), np.array([34.3, 20, 26.6]), (20.0, 20.0, 0.0), (1.0, 0.0, 0.0),
                            (40, 40, 30), [1.8, 3, 4.5], 1.2, 28.8)
    assert sorted({r for _, r in sph}) == [1.8, 3.0, 4.5]
    # a specimen described as one region: no cap (a 24 mm wide image of one, tracked over
    # 12.8 mm, capped the radius at 2.56 mm, under a hidden sphere of 4 mm)
    lo, hi = np.array([13.6, 20.0, 3.0]), np.array([26.4, 20.0, 25.0])
    assert capping_width(lo, hi, [1.0, 0.0, 0.0], 2) == pytest.approx(12.8)
    assert capping_width(lo, hi, [1.0, 0.0, 0.0], 1) == math.inf
    sph = candidate_spheres(lo, hi, (20.0, 20.0, 0.0), (1.0, 0.0, 0.0), (40, 40, 30), [1.8, 3, 4.5], 1.2,
                            capping_width(lo, hi, [1, 0, 0], 1))
    assert sorted({r for _, r in sph}) == [1.8, 3.0, 4.5]


def test_the_scan_and_the_placement_move_spheres_in_the_image_plane_of_a_turned_probe():
    """With the probe turned along y (lateral axis (0, -1, 0)), the image plane is
    x = the probe's x: the scan's centres keep that x and spread along y over the
    tracked field and beyond (they were all put on the probe's axis, y = its
    centre, before: a blind paper-size phantom with the probe along y located a
    sphere 8 mm off the axis at the axis); the same grid as a probe along x, turned.
    The placement's in-plane coordinates are exact for a probe along x."""
    from app.core.effects.inclusion import candidate_spheres, plane_coordinates, plane_point

    size, step, radii = (90.0, 90.0, 96.0), 3.6, [5.4]
    lo_x, hi_x = np.array([28.7, 50.0, 63.6]), np.array([60.7, 50.0, 92.4])  # probe at (44.7, 50) along x
    along_x = candidate_spheres(lo_x, hi_x, (44.7, 50.0, 0.0), (1.0, 0.0, 0.0), size, radii, step, 32.0)
    lo_y, hi_y = np.array([38.0, 29.3, 63.6]), np.array([38.0, 61.3, 92.4])  # probe at (38, 45.3) along -y
    along_y = candidate_spheres(lo_y, hi_y, (38.0, 45.3, 0.0), (0.0, -1.0, 0.0), size, radii, step, 32.0)
    C = np.array([c for c, _ in along_y])
    assert np.all(C[:, 0] == 38.0), C[:, 0]
    assert C[:, 1].min() < lo_y[1] - 3.0 and C[:, 1].max() > hi_y[1] + 3.0  # along the field, and beyond
    assert len(along_y) == len(along_x)
    # a sphere 8 mm to the side of the probe's centre, 12 mm deep, has a scanned centre within a step
    assert np.min(np.linalg.norm(C - np.array([38.0, 53.3, 84.0]), axis=1)) < step
    for center, lateral in (([31.25, 45.0, 82.5], (1.0, 0.0, 0.0)), ([38.0, 58.0, 84.0], (0.0, -1.0, 0.0))):
        base, s, z = plane_coordinates(center, lateral)
        assert base[2] == 0.0 and z == center[2]
        assert list(plane_point(base, lateral, s, z)) == pytest.approx(center, abs=1e-12)
    base, s, z = plane_coordinates([31.25, 45.0, 82.5], (1.0, 0.0, 0.0))
    assert (s, z, list(base)) == (31.25, 82.5, [0.0, 45.0, 0.0])
    assert list(plane_point(base, (1.0, 0.0, 0.0), s + 1.5, z)) == [32.75, 45.0, 82.5]  # exactly


def test_a_located_inclusion_is_meshed_with_the_looser_envelope_and_the_fine_outline(monkeypatch):
    """current_model() with an inclusion and automatic settings meshes with
    LOCATED_EPSILON and the probe face's outline at FINE_OUTLINE_MM, as the
    automatic meshes have it (the candidate and the added version alike);
    explicit settings are kept as given."""
    from dataclasses import replace

    from app.core import diagnose as dg
    from app.core.effects.inclusion import inclusion_region
    from app.core.mesh import auto_settings

    seen = []
    monkeypatch.setattr(dg.EffectProblem, "from_experiment",
                        classmethod(lambda cls, exp, **kw: seen.append((exp, kw["mesh_settings"]))))
    exp = read_experiment(synthetic.diagnose_case("inclusion"))
    inc = {"name": "I", "center_mm": [26.0, 20.0, 14.0], "radius_mm": 4.5}
    dg.current_model(exp, inclusion=inc)
    with_sphere, settings = seen[-1]
    assert with_sphere.specimen.region_names[-1] == "I"
    auto = auto_settings(with_sphere.specimen.size_mm, with_sphere.probe.face_rect_mm(), with_sphere.specimen.regions)
    assert settings.epsilon == dg.LOCATED_EPSILON > auto.epsilon
    assert (settings.edge_mm, settings.probe_edge_mm) == (auto.edge_mm, auto.probe_edge_mm)
    # the face's own size here is 1.6 mm; its outline at 1.0 mm, as in every automatic mesh
    assert (auto.probe_edge_mm, auto.outline_edge_mm, settings.outline_edge_mm) == (1.6, 1.0, 1.0)
    demo = read_experiment(ROOT / "resources" / "demo")  # paper size: the face at 2.0 mm, its outline at 1.0
    paper = dg.located_inclusion_settings(replace(demo, specimen=demo.specimen.with_region(inclusion_region(inc))))
    assert (paper.probe_edge_mm, paper.outline_edge_mm) == (2.0, 1.0)
    fine = replace(exp, probe=replace(exp.probe, face_mm=(4.0, 4.0)))  # a face meshed finer than 1 mm keeps its size
    assert dg.located_inclusion_settings(fine).outline_edge_mm is None
    dg.current_model(exp, inclusion=inc, mesh_settings=ID_MESH)
    assert seen[-1][1] == ID_MESH
    dg.current_model(exp)  # no inclusion: the experiment's own automatic settings
    assert seen[-1][1] is None


def test_a_model_with_the_inclusion_effect_needs_the_inclusions_place():
    """Without a located inclusion the model would be the one without it, named
    with it (what `identify --effects inclusion` once returned): refused, before
    any meshing."""
    from app.core.effects.model import EffectProblem

    exp = read_experiment(synthetic.diagnose_case("inclusion"))
    with pytest.raises(ElastoidError, match="needs the inclusion's place"):
        EffectProblem.from_experiment(exp, effects=("inclusion",), mesh_settings=ID_MESH)


def test_the_scan_fits_each_sphere_under_the_diagnosis_huber_loss():
    """huber_fits against scipy's general minimizer of the same loss (an independent
    check), on misfits with outliers, for several column sets at once, two of whose
    columns sum to nothing (as the described regions' patterns do: stiffening every
    region alike moves no block)."""
    from scipy.optimize import minimize

    from app.core.effects.inclusion import huber_fits, huber_loss

    rng = np.random.default_rng(3)
    n, c = 300, 2.0
    base = rng.normal(size=n)
    X = np.stack([np.stack([base, -base, rng.normal(size=n)], axis=1) for _ in range(4)], axis=2)
    X[:, 2, 1] = X[:, 2, 0] + 0.3 * rng.normal(size=n)  # a close rival column
    y = 1.5 * X[:, 2, 0] + 0.7 * base + rng.normal(size=n)
    y[:20] += rng.choice([-12.0, 12.0], size=20)  # outliers beyond 3 sigma, as a badly tracked block is
    loss, b = huber_fits(X, y, c)
    for j in range(X.shape[2]):
        A = X[:, [0, 2], j]  # the dependent column dropped: the same span
        ref = minimize(lambda v: float(huber_loss(y - A @ v, c)), np.zeros(2), method="Nelder-Mead",
                       options={"xatol": 1e-10, "fatol": 1e-10, "maxiter": 20000})
        assert loss[j] == pytest.approx(ref.fun, rel=1e-7)
        assert b[2, j] == pytest.approx(ref.x[1], abs=1e-5)
        assert b[0, j] - b[1, j] == pytest.approx(ref.x[0], abs=1e-5)
    assert b[2, 0] == pytest.approx(1.5, abs=0.15)  # the outliers barely move it
    assert loss[0] < loss[1]  # the column that made the data fits it best
    assert huber_loss(np.array([1.0, -3.0]), 2.0) == pytest.approx(1.0 + (2 * 2 * 3 - 4))


def test_a_sphere_elsewhere_that_fits_nearly_as_well_is_reported():
    """The scan reports a non-overlapping sphere that explains RIVAL_SHARE of what the
    best explains, and the evidence and the inclusion's dict say so. The scores are
    the out-of-view paper-size seed's (16xxx `incl`, 2026-11-29): a softer sphere
    right of the field 284.4, a stiffer one left of it 266.5 (the truth is there)."""
    from app.core.effects.inclusion import RIVAL_SHARE, InclusionGuess, also_fits_text, best_and_rival, evidence

    right, left = np.array([64.7, 45.0, 78.0]), np.array([21.5, 45.0, 74.4])
    scored = [(284.4, right, 6.4, -0.79), (282.0, right, 5.4, -1.32),  # the same place, another radius
              (268.9, right + [0, 0, 3.6], 6.4, -0.6),  # overlapping: the same place too
              (266.5, left, 5.4, 1.94), (120.0, np.array([45.0, 45.0, 60.0]), 5.4, 0.5)]
    best, rival = best_and_rival(scored)
    assert best[0] == 284.4 and rival[0] == 266.5 and rival[3] > 0
    assert best_and_rival([t for t in scored if t[0] != 266.5])[1] is None  # 120 is not within RIVAL_SHARE
    assert best_and_rival([(100.0, right, 6.4, 1.0), (RIVAL_SHARE * 100.0 - 0.1, left, 5.4, 1.0)])[1] is None
    g = InclusionGuess("I", tuple(right), 6.4, False, 284.4, (tuple(left), 5.4, True, 266.5))
    inc = g.as_inclusion()
    assert inc["also_fits"] == {"center_mm": [21.5, 45.0, 74.4], "radius_mm": 5.4, "stiffer": True,
                                "explained": 266.5, "explained_here": 284.4}
    text = also_fits_text(inc, 96.0)
    assert text == ("a stiffer region about 11 mm across at 22 mm depth, 43 mm from it, explains the misfit nearly "
                    "as well (266 against 284 on the scan): these measurements do not tell the two places apart")
    said = evidence(g, 18.0, 0.3, 0.35, 0.15, text)
    assert said.endswith("falls from 0.35 to 0.15 px; but " + text)
    clear = InclusionGuess("I", tuple(left), 5.4, True, 300.0)
    assert "also_fits" not in clear.as_inclusion() and also_fits_text(clear.as_inclusion(), 96.0) == ""


def test_the_rival_place_fitted_too_is_kept_as_what_it_did():
    """Both places of an ambiguous scan are meshed and fitted (diagnose._try_inclusion);
    the one that lowers chi2 more is the candidate, and its inclusion says what the
    other did: still ``also_fits`` when it explains RIVAL_SHARE as much, else
    ``rival_fitted``, a place tried that fits worse. The rival of a guess is a guess
    whose rival is the first."""
    from app.core.effects.inclusion import RIVAL_SHARE, InclusionGuess, also_fits_text, with_fitted_rival

    best, other = (43.1, 45.0, 74.4), (46.7, 45.0, 56.4)
    g = InclusionGuess("I", best, 6.4, False, 380.6, (other, 6.4, True, 375.7))
    r = g.rival_guess()
    assert r.center_mm == other and r.stiffer and r.explained == 375.7
    assert r.rival == (best, 6.4, False, 380.6) and r.rival_guess() == g
    assert InclusionGuess("I", best, 6.4, False, 380.6).rival_guess() is None

    placed = {"name": "I", "center_mm": list(best), "radius_mm": 6.4,
              "also_fits": r.as_inclusion()["also_fits"]}  # the scan's words, replaced
    rival = r  # the rival place, as the diagnosis fitted it
    resolved = with_fitted_rival(placed, rival, 520.0, 300.0)
    assert "also_fits" not in resolved and resolved["rival_fitted"] == {
        "center_mm": list(other), "radius_mm": 6.4, "stiffer": True, "explained": 300.0, "explained_here": 520.0,
        "fitted": True}
    assert {k: resolved[k] for k in ("name", "center_mm", "radius_mm")} == {k: placed[k] for k in
                                                                          ("name", "center_mm", "radius_mm")}
    assert also_fits_text(resolved, 96.0) == (
        "a stiffer region about 13 mm across at 40 mm depth, 18 mm from it, which the scan ranked about as high, "
        "was meshed and fitted too and explains less (chi2 falls by 300 there against 520 here)")
    tied = with_fitted_rival(placed, rival, 520.0, RIVAL_SHARE * 520.0)
    assert "rival_fitted" not in tied and tied["also_fits"]["fitted"]
    assert also_fits_text(tied, 96.0) == (
        "a stiffer region about 13 mm across at 40 mm depth, 18 mm from it, meshed and fitted too, explains the "
        "misfit nearly as well (chi2 falls by 468 there against 520 here): these measurements do not tell the two "
        "places apart")
    # neither explains anything: no ambiguity to report
    assert "rival_fitted" in with_fitted_rival(placed, rival, -5.0, -8.0)


def test_an_inclusion_verdict_on_a_coarse_outline_says_its_modulus_rests_on_that_mesh():
    """At four hidden spheres' true places the automatic meshes (the probe face's
    outline at 2.0 mm) gave the sphere's modulus 15-89% low, and 1.0 mm along the
    outline within 25% (docs/model-check.md): an inclusion verdict identified on an
    outline coarser than FINE_OUTLINE_MM says so, with the size used; one on a
    fine outline, or an old session's without the size, does not."""
    from app.core.diagnose import Candidate, Diagnosis, NoiseModel
    from app.core.mesh import FINE_OUTLINE_MM as OUTLINE_ADVISED_MM

    place = {"name": "I", "center_mm": [64.7, 45.0, 81.6], "radius_mm": 6.4}
    base = Candidate("", (), {"E_B_kPa": 17.9, "E_A_kPa": 63.8}, {}, {"chi2": 3000.0})

    def verdict(outline):
        inc = Candidate("inclusion", ("inclusion",), {"E_B_kPa": 18.0, "E_A_kPa": 63.7, "E_I_kPa": 6.7}, {},
                        {"chi2": 1800.0}, 4, 900.0, "", place, material=True)
        inc.identified = {"parameters": {"E_B_kPa": 18.0, "E_A_kPa": 63.8, "E_I_kPa": 11.0}, "cost": {"total": -1.05},
                          "seconds": 80.0, "place_trials": 16}
        if outline is not None:
            inc.identified["outline_mm"] = outline
        return Diagnosis("x", base, [inc], "inclusion", NoiseModel(0.02, 1481, 0.2, 200), 1.0)

    text = verdict(2.0).identified_text()
    assert ("E_I rests on the mesh along the probe face's outline (2 mm here) more than on the frames: mesh the "
            f"outline at {OUTLINE_ADVISED_MM:g} mm, or check the mesh, to see how far it moves") in text, text
    for fine in (OUTLINE_ADVISED_MM, 0.8, None):
        assert "rests on the mesh" not in verdict(fine).identified_text()
    d = verdict(2.0)
    assert Diagnosis.from_state(d.state()).identified_text() == text  # a session file keeps it


def test_an_inclusion_verdict_at_the_probes_contact_says_a_slip_fits_too():
    """Numbers from blind face-slip+52000 (a probe slip hidden under a 30 x 14 mm
    face; docs/model-check.md, "A fresh blind sweep"): the verdict was a soft
    sphere placed at (29.2, 45, 88.8) mm, radius 6.4, its top 0.8 mm under the
    surface at the face's edge (x 30), scoring +985 against the slip's +678. The
    verdict stands (a real inclusion can lie there), and the report says that a
    region there changes the contact as a slip does; away from the face, or with
    the slip no finding, it says nothing."""
    from dataclasses import replace

    from app.core.diagnose import Candidate, Diagnosis, NoiseModel, contact_of
    from app.core.effects.inclusion import at_contact, contact_gaps
    from app.core.export import verdict_html
    from app.gui.models.modelcheck import verdict_parts

    exp = read_experiment(ROOT / "resources" / "demo")
    exp = replace(exp, probe=replace(exp.probe, face_mm=(30.0, 14.0)))
    face = exp.probe.face_rect_mm()
    assert face == (30.0, 60.0, 38.0, 52.0)
    placed = {"name": "I", "center_mm": [29.15, 45.0, 88.8], "radius_mm": 6.4}
    assert contact_gaps(placed, exp.specimen.size_mm, face) == pytest.approx((0.8, 0.85))
    assert at_contact(placed, exp.specimen.size_mm, face)
    # 8 mm deep (a blind phantom's hidden sphere), or a sphere's width beside the face: not at the contact
    assert not at_contact({**placed, "center_mm": [45.0, 45.0, 82.0]}, exp.specimen.size_mm, face)
    assert not at_contact({**placed, "center_mm": [22.0, 45.0, 88.8]}, exp.specimen.size_mm, face)

    mis = {"chi2": 2386.2, "force_rms_N": 0.0195, "displacement_rms_px": 0.5}
    incl = Candidate("inclusion", ("inclusion",), {"E_B_kPa": 17.97}, {}, mis, 4, 985.492, "a softer region",
                     inclusion={"name": "I", "center_mm": [28.7, 45.0, 88.8], "radius_mm": 6.4}, material=True,
                     identified={"parameters": {"E_B_kPa": 18.01, "E_A_kPa": 66.13, "E_I_kPa": 8.85}, "cost": {},
                                 "seconds": 95.7, "inclusion": placed})
    slip = Candidate("probe-slip", ("probe-slip",), {"E_B_kPa": 17.79}, {}, {**mis, "chi2": 2825.9}, 1, 677.699,
                     "slides", material=True)
    k = contact_of([incl, slip], "inclusion", exp)
    assert k == {"effect": "probe-slip", "score": 677.699, "verdict_score": 985.492, "top_gap_mm": 0.8,
                 "outside_mm": 0.85}
    base = Candidate("", (), {"E_B_kPa": 18.0}, {}, {**mis, "chi2": 3509.5})
    d = Diagnosis("x", base, [incl, slip], "inclusion", NoiseModel(0.02, 1481, 0.236, 318), 1.0, contact=k)
    text = d.contact_advice()
    assert text.startswith("the inclusion lies at the edge of the probe's face, its top 0.8 mm under the surface")
    assert "probe-slip earns its parameters too (score +678 against +985)" in text
    assert "the scores do not settle it" in text and "a sloping surface), add probe-slip instead. " in text
    # with the outline at 0.5 mm face-slip+52000 became probe-slip and a real sphere there (53001) stayed an inclusion
    assert text.endswith("diagnose again with it at 0.5 mm (the mesh's outline size, --outline-edge-mm 0.5), which "
                         "named the slip where a slip was and kept the sphere where a sphere was on two simulated "
                         "phantoms")
    assert f"contact: {text}" in d.lines() and d.to_json_dict()["contact"] == k
    assert Diagnosis.from_state(json.loads(json.dumps(d.state()))).contact == k
    parts = verdict_parts(d)
    assert parts[3] == f"At the probe's contact: {text}."
    assert "\u26a0 At the probe&#x27;s contact: the inclusion lies" in verdict_html(parts)
    # the slip no finding, another verdict, or the sphere deeper: nothing to say
    assert contact_of([incl, replace(slip, score=-5.0)], "inclusion", exp) is None
    assert contact_of([incl, replace(slip, material=False)], "inclusion", exp) is None
    assert contact_of([incl, slip], "probe-slip", exp) is None
    deeper = replace(incl, identified={**incl.identified, "inclusion": {**placed, "center_mm": [29.15, 45.0, 84.0]}})
    assert contact_of([deeper, slip], "inclusion", exp) is None
    assert Diagnosis("x", base, [incl, slip], "inclusion", d.noise, 1.0).contact_advice() == ""
