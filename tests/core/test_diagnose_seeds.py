"""Diagnoses of whole seeds: data with no hidden effect (every candidate of the
catalogue, the verdict must be none) and two effects hidden at once (found one
after the other). Split from test_diagnose.py so that the two pytest-xdist
workers (``--dist loadfile`` sends a file to one worker) share the
diagnoses; the experiments and meshes are the same committed ones (see
test_diagnose.py)."""

import json

import pytest

from app.core.diagnose import ModelCheck, ModelHistory, diagnose
from app.core.effects import EFFECT_IDS
from app.core.simulate import read_truth
from tests.core.synthetic import DIAGNOSE_FAST as FAST
from tests.core.synthetic import DIAGNOSE_ID_MESH as ID_MESH
from tests.core.synthetic import assert_mesh_committed
from tests.core.synthetic import diagnose_experiment as _make
from tests.core.synthetic import moduli_errors as _moduli_errors

_DIAGNOSED = {}


def _diagnosed(tmp_path_factory, case):
    """The full diagnosis of the committed experiment ``case``, once per module."""
    if case not in _DIAGNOSED:
        _DIAGNOSED[case] = diagnose(_make(tmp_path_factory, case), mesh_settings=ID_MESH)
    return _DIAGNOSED[case]


@pytest.mark.parametrize("case", ["none-5", "none-6", "none-17", "e-none-27", "e-none-29"])
def test_no_hidden_effect_gives_none(tmp_path_factory, case):
    """Every candidate of the catalogue (38 s per seed here, 2026-11-25; 56 s on
    the soft ellipsoid, seed 27). The spheres the scans locate are meshed as
    regions; their meshes are committed (fTetWild is not deterministic).

    Seed 17 (2026-11-26) was a false positive before a fitted Poisson's ratio
    had to move at least 0.02 from the model's: compressibility at nu 0.482
    scored +55.4 and removed 48% of the error beyond the noise (the mesh error;
    every seed here fits nu 0.482-0.487).

    The located spheres of seeds 6, 17 and 29 were not committed and were meshed
    afresh in every run until 2026-11-27, when one run's mesh of seed 17's sphere
    gave a false inclusion (+13.9). Over six meshes of it the inclusion scored -17.5
    to +13.9; the committed one scored -1.5 (docs/model-check.md, "Where the
    diagnosis stops"). Since weak blocks are confirmed by a larger block
    (2026-11-29) the scans of two seeds put their spheres elsewhere, meshed
    afresh again until the next day: the test now checks that every located
    sphere's mesh is committed."""
    d = _diagnosed(tmp_path_factory, case)
    located = d.candidate("inclusion").inclusion
    if located is not None:
        assert_mesh_committed(d.baseline.problem.exp, located)
    assert {c.effect for c in d.candidates} == set(EFFECT_IDS), d.lines()
    assert d.verdict == "none", d.lines()
    # nothing material: whatever scores above zero explains little of the error beyond the noise
    assert not any(c.material and c.score > 0 for c in d.candidates), d.lines()
    # and no boundary effect is said to hide an inclusion (the masked-pair screen ran: the verdict is none)
    assert d.masked is None and "hide each other" not in d.none_text(), d.lines()
    assert {s["effect"] for s in d.masked_screen} == {"probe-slip", "sliding-bottom"}, d.masked_screen
    assert all(s["margin"] <= s["needed"] for s in d.masked_screen), d.masked_screen


def test_a_new_mesh_alone_is_not_credited_to_an_inclusion(tmp_path_factory):
    """Seed 5 has no hidden effect. The sphere its scan locates, meshed as a region,
    lowers the chi2 from 993 to 902: the new mesh alone (the current model refitted
    on it) takes it to 916, and the sphere's 4 parameters cost 26.5. Scored against
    the current model on the same mesh the inclusion earns nothing (-12.6; +64.5 and
    the verdict inclusion when it was scored against the current model on its own
    mesh). The located sphere's mesh is committed (fTetWild is not deterministic)."""
    d = _diagnosed(tmp_path_factory, "none-5")  # every candidate: the inclusion's score is its own
    assert d.verdict == "none", d.lines()
    c = d.candidate("inclusion")
    assert c.reference is not None and c.reference["chi2"] < d.baseline.misfit["chi2"] - 30, d.lines()
    assert c.score < 0, d.lines()
    assert "explains little" in c.evidence or "does not explain" in c.evidence, c.evidence
    payload = {c["effect"]: c for c in d.to_json_dict()["candidates"]}
    assert "reference_misfit" in payload["inclusion"]


TWO_CASES = [("two", ("viscoelastic", "sliding-bottom"), FAST),
             ("two-16", ("compressibility", "viscoelastic"), FAST + ("compressibility",)),
             ("e-two", ("viscoelastic", "sliding-bottom"), FAST)]


@pytest.mark.parametrize("case,pair,candidates", TWO_CASES, ids=[c[0] for c in TWO_CASES])
def test_two_hidden_effects_are_found_one_after_the_other(tmp_path_factory, case, pair, candidates):
    """Two effects hidden at once (seed 3: the tissue relaxes and the specimen
    slides on the table; seed 16: the tissue relaxes and is compressible, nu 0.3;
    seed 28: relaxation and sliding on the soft ellipsoid). The first diagnosis
    names one; once it is added, the second names the other, and with both the
    error falls and the moduli come right.

    Measured: seed 3 on fresh meshes (bench/diagnose_effects.py
    viscoelastic+sliding-bottom 3): viscoelastic then sliding-bottom, moduli
    within 6% (the baseline's E_A was +170%), force error beyond the noise 7.1x
    lower, displacement error 6.4x. On the committed data (2026-11-26): seed 16,
    compressibility (nu 0.30) then viscoelastic, moduli -1.7%, +0.6% (baseline
    -31%, -38%), force 8.8x, displacement 14x; seed 28, viscoelastic then
    sliding-bottom, moduli +2.3%, -8.0% (baseline -32%, +234%), force to the
    noise, displacement 11x."""
    exp = _make(tmp_path_factory, case)
    mc = ModelCheck(exp, mesh_settings=ID_MESH)
    mc.identify(())
    first = mc.diagnose(candidates=candidates)
    assert first.verdict in pair, first.lines()
    mc.add()
    second = mc.diagnose(candidates=candidates)
    other = (set(pair) - {first.verdict}).pop()
    assert second.verdict == other, second.lines()
    v = mc.add()
    assert set(v.effects) == set(pair)
    errs = mc.history.errors()
    assert errs["force_excess_N"][-1] < errs["force_excess_N"][0] / 3.0, errs
    assert errs["displacement_excess_px"][-1] < errs["displacement_excess_px"][0] / 3.0, errs
    for region, err in _moduli_errors(v.parameters, read_truth(exp.path)["moduli_kPa"]).items():
        assert abs(err) < 0.10, (region, err, second.lines())


def test_a_slip_and_an_inclusion_that_hide_each_other_are_found_by_following_the_screen(tmp_path_factory,
                                                                                        monkeypatch):
    """Seed 30: the probe slips on the surface, and a stiffer sphere (60 kPa in
    15 kPa tissue, radius 4 mm) lies 5 mm under the probe's right end. Fitted
    alone, each candidate fails: the slip fits worse than the bonded model, and
    the inclusion is placed elsewhere. The masked-pair screen, which scans the
    slipping model's misfit, names probe-slip and the sphere's place; adding
    probe-slip as it says, the next diagnosis finds the inclusion.

    Measured on the committed data and meshes (2026-11-29): the first verdict
    none, the screen's margin 300 (33 needed), its sphere 0.1 mm from the truth;
    then the inclusion (+593), 0.1 mm off, E_I 41 for 60; moduli -1.2% and -7.0%;
    the displacement error beyond the noise 0.336 -> 0.097 px (3.5x) and the chi2
    1,445 -> 895 from the baseline. The same seed with fresh meshes gave the
    same first diagnosis (margin 191), as did two more placements (seeds 31 and
    32, a stiff sphere under the left end and an 8 kPa one under the right)."""
    import numpy as np

    from app.core import diagnose as diagnose_module

    # the identification's placement of the sphere runs three trials here (its search is
    # tested in test_diagnose.py); what this test needs is the placed sphere added
    # through mc.add(). Its sixteen trials took 60 s of this test's 110 in CI
    monkeypatch.setattr(diagnose_module, "PLACE_MAX_TRIALS", 3)
    exp = _make(tmp_path_factory, "slip-inclusion")
    c_true = np.array(read_truth(exp.path)["hidden_regions"][0]["center_mm"])
    candidates = ("inclusion", "probe-slip")
    mc = ModelCheck(exp, mesh_settings=ID_MESH)
    mc.identify(())
    first = mc.diagnose(candidates=candidates)
    assert first.verdict in ("none", "inclusion"), first.lines()
    assert first.masked is not None and first.masked["effect"] == "probe-slip", (first.masked_screen, first.lines())
    assert np.linalg.norm(np.array(first.masked["inclusion"]["center_mm"]) - c_true) < 3.0, first.masked
    assert first.masked["stiffer"] is True
    said = first.none_text() if first.verdict == "none" else first.masked_text()
    assert "hide each other" in said and "add probe-slip and diagnose again" in said.lower(), said
    # the screen's figures: the slip's pair beat the best single effect by more than it needs
    (screen,) = first.masked_screen
    assert screen["effect"] == "probe-slip" and screen["margin"] > screen["needed"], first.masked_screen
    v = mc.add("probe-slip")
    # alone, the slip fits worse: the version says that was expected, and what to do next
    assert "as the diagnosis expected" in v.warning and "Diagnose again" in v.warning, v.warning
    second = mc.diagnose(candidates=candidates)
    assert second.verdict == "inclusion", second.lines()
    c = second.candidate("inclusion")
    assert_mesh_committed(second.baseline.problem.exp, c.inclusion)
    assert np.linalg.norm(np.array(c.inclusion["center_mm"]) - c_true) < 3.0, c.inclusion
    # the placement (three trials) moved the sphere where the identification's cost is lower
    placed = second.identified["inclusion"]
    assert second.identified["cost"]["total"] < second.identified["located_cost"]["total"], second.identified
    v = mc.add()
    assert {k: v.inclusion[k] for k in placed} == placed, (v.inclusion, placed)  # the version's sphere
    assert set(v.effects) == {"probe-slip", "inclusion"}
    # the identification moved the sphere: the version sits on the located sphere's mesh, relabelled, and
    # a session read back rebuilds that same model (meshing the moved sphere would make another one)
    assert v.inclusion["center_mm"] != c.inclusion["center_mm"], (v.inclusion, c.inclusion)
    assert v.inclusion["meshed_at"] == {k: c.inclusion[k] for k in ("center_mm", "radius_mm")}, v.inclusion
    # what ModelCheck.restored does for the current version (_problem -> _build), from the version as a session
    # file keeps it; a fresh check, so nothing of this one's models is shared
    saved = ModelHistory.from_json_dict(json.loads(json.dumps(mc.history.to_json_dict()))).current_version
    assert saved.inclusion == v.inclusion
    live = mc.problem
    fresh = ModelCheck(exp, mesh_settings=ID_MESH)
    rebuilt = fresh._build(saved.effects, saved.inclusion, None, None, saved.parameters)
    assert rebuilt.mesh.region_names == live.mesh.region_names, rebuilt.mesh.region_names
    for name in ("points_mm", "tets", "labels"):
        assert np.array_equal(getattr(rebuilt.mesh, name), getattr(live.mesh, name)), name
    assert np.allclose(rebuilt.model_force_N(v.parameters), live.model_force_N(v.parameters), rtol=1e-4), \
        "the rebuilt model predicts another force"
    rebuilt.release()
    errs = mc.history.errors()
    assert errs["displacement_excess_px"][-1] < errs["displacement_excess_px"][0] / 3.0, errs
    truth = read_truth(exp.path)["moduli_kPa"]
    for region, err in _moduli_errors(v.parameters, {k: truth[k] for k in ("B", "A")}).items():
        assert abs(err) < 0.10, (region, err, second.lines())
