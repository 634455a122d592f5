"""The batch command line: simulate, identify, their JSON, and clear errors."""

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from app.cli import main

ROOT = Path(__file__).resolve().parent.parent


def test_simulate_then_identify_json_follows_the_contract(tmp_path, capsys):
    out = tmp_path / "exp"
    assert main(["simulate", str(out), "--size-mm", "40,40,30", "--inclusion", "sphere:20,20,18,7",
                 "--moduli", "B=15,A=45", "--face-mm", "24,8", "--depth-mm", "5", "--frames-at", "0,2.5,5",
                 "--rows", "128", "--cols", "120", "--seed", "1", "--quiet"]) == 0
    assert (out / "truth.toml").is_file() and (out / "experiment.toml").is_file()
    capsys.readouterr()
    assert main(["identify", str(out), "--json", "-", "--starts", "10,30", "--quiet"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert set(result) >= {"experiment", "effects", "parameters", "cost", "evaluations", "seconds"}
    assert result["effects"] == []
    assert set(result["parameters"]) == {"E_B_kPa", "E_A_kPa"}
    assert set(result["cost"]) >= {"total", "nmi", "force_rms_N"}
    # the joint cost is -NMI plus the force misfit relative to the peak force (docs/cli.md)
    from app.core.experiment import read_experiment

    peak = float(abs(read_experiment(out).force_log.force_N).max())
    c = result["cost"]
    assert c["total"] == pytest.approx(-c["nmi"] + (c["force_rms_N"] / peak) ** 2, abs=1e-9)
    assert c["nmi"] > 1.02  # the warped source agrees with the frames far beyond chance (unrelated: ~1.00)
    assert result["evaluations"] > 10 and result["seconds"] > 0
    assert result["frames"] == [0, 1, 2]  # the source first, then every deeper frame
    assert all(math.isfinite(v) for v in result["parameters"].values())


def test_simulate_an_off_centre_probe_turned_a_quarter_turn_and_identify_it(tmp_path, capsys):
    """The probe need not sit at the top's centre nor along x: the simulator writes
    such an experiment (--probe-center-mm, --probe-turn-deg) and the identification
    finds the moduli from it (measured: E_B -2.3%, E_A +5.0% of 15 and 45 kPa)."""
    from app.core.experiment import read_experiment

    out = tmp_path / "exp"
    assert main(["simulate", str(out), "--size-mm", "40,40,30", "--inclusion", "sphere:20,20,18,7",
                 "--moduli", "B=15,A=45", "--face-mm", "24,8", "--depth-mm", "5", "--frames-at", "0,2.5,5",
                 "--rows", "128", "--cols", "120", "--seed", "1", "--probe-center-mm", "17,22", "--probe-turn-deg", "90",
                 "--quiet"]) == 0
    probe = read_experiment(out).probe
    assert probe.center_mm == (17.0, 22.0) and probe.lateral_axis == (0.0, 1.0, 0.0)
    assert probe.face_rect_mm() == (13.0, 21.0, 10.0, 34.0)  # the face's 24 mm along y
    capsys.readouterr()
    assert main(["identify", str(out), "--json", "-", "--starts", "10,30", "--quiet"]) == 0
    p = json.loads(capsys.readouterr().out)["parameters"]
    assert p["E_B_kPa"] == pytest.approx(15.0, rel=0.10) and p["E_A_kPa"] == pytest.approx(45.0, rel=0.10), p


def test_demo_identification_finds_the_reference_moduli(tmp_path, capsys):
    """The README's main job: the paper-like demo, joint cost, the paper's six starts."""
    dest = tmp_path / "result.json"
    assert main(["identify", str(ROOT / "resources" / "demo"), "--json", str(dest), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "E_A_kPa" in printed and "reference 63.0 kPa" in printed
    result = json.loads(dest.read_text())
    assert result["parameters"]["E_B_kPa"] == pytest.approx(18.0, rel=0.05)
    assert result["parameters"]["E_A_kPa"] == pytest.approx(63.0, rel=0.05)
    assert len(result["starts"]) == 6


def test_bad_experiment_gives_a_message_naming_file_and_field(tmp_path, capsys):
    assert main(["identify", str(tmp_path / "nothing")]) == 2
    assert "nothing" in capsys.readouterr().err
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "experiment.toml").write_text('format = "elastoid-experiment/1"\n[specimen]\nsize_mm = [1, -2, 3]\n')
    assert main(["identify", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "experiment.toml" in err and "specimen.size_mm" in err and "Traceback" not in err


def test_unknown_or_unavailable_effect_is_refused(capsys):
    assert main(["identify", str(ROOT / "resources" / "demo"), "--effects", "magic"]) == 2
    assert "unknown effect 'magic'" in capsys.readouterr().err


def test_simulate_inclusion_needs_the_hidden_region(tmp_path, capsys):
    assert main(["simulate", str(tmp_path / "x"), "--effects", "inclusion", "--quiet"]) == 2
    assert "--hidden" in capsys.readouterr().err
    assert main(["simulate", str(tmp_path / "y"), "--hidden", "box:1,2,3", "--quiet"]) == 2
    assert "--hidden: expected sphere" in capsys.readouterr().err
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


def test_simulate_a_hidden_inclusion(tmp_path):
    from app.core.experiment import read_experiment
    from app.core.simulate import read_truth

    out = tmp_path / "exp"
    assert main(["simulate", str(out), "--size-mm", "40,40,30", "--inclusion", "sphere:20,20,18,7",
                 "--moduli", "B=15,A=45", "--face-mm", "24,8", "--depth-mm", "3", "--frames-at", "0,3",
                 "--rows", "96", "--cols", "96", "--hidden", "sphere:28,20,12,3,60", "--quiet",
                 # what is checked here is what the command writes; the default truth mesh
                 # (0.7 of the automatic size, 1.2 mm inside a 3 mm sphere) takes 80 s and 4.8 GB
                 "--truth-mesh-scale", "1.5"]) == 0
    truth = read_truth(out)
    assert truth["effects"] == ["inclusion"] and truth["moduli_kPa"]["H"] == 60.0
    assert truth["hidden_regions"][0]["center_mm"] == [28.0, 20.0, 12.0]
    exp = read_experiment(out)
    assert exp.specimen.region_names == ("B", "A")  # the experiment does not describe it
    # its name says what the experiment describes, not what is hidden (it said "stiff inclusion" whatever the specimen)
    assert exp.name == "Synthetic phantom, 40 x 40 x 30 mm, region A (sphere) in B"


@pytest.mark.parametrize("command", ["identify", "diagnose"])
def test_a_json_destination_that_cannot_be_written_is_refused_before_the_run(tmp_path, capsys, monkeypatch, command):
    """A batch must not run for hours to fail at its last line: the --json file's
    folder is checked first, and the run never starts."""
    import app.core.diagnose
    import app.core.identify

    def must_not_run(*a, **k):
        raise AssertionError("the run started")

    monkeypatch.setattr(app.core.identify, "identify", must_not_run)
    monkeypatch.setattr(app.core.diagnose, "diagnose", must_not_run)
    demo = str(ROOT / "resources" / "demo")
    missing = tmp_path / "no-such-folder" / "result.json"
    assert main([command, demo, "--json", str(missing), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "--json" in err and str(missing) in err and "does not exist" in err and "Traceback" not in err
    assert main([command, demo, "--json", str(tmp_path), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "--json" in err and "is a folder" in err
    assert not missing.parent.exists()


def test_a_result_that_cannot_be_written_at_the_end_is_not_lost(tmp_path, capsys):
    """The folder can go (or the disk fill) during a run: the result then goes to
    standard output, the reason to standard error; a file is never half written."""
    from app.cli import _write_json

    payload = {"verdict": "viscoelastic", "candidates": [{"effect": "viscoelastic", "score": 12.5}]}
    gone = tmp_path / "gone" / "result.json"
    assert _write_json(str(gone), payload) is False
    out, err = capsys.readouterr()
    assert json.loads(out) == payload
    assert str(gone) in err and "standard output" in err
    dest = tmp_path / "result.json"
    dest.write_text("an older result\n")
    assert _write_json(str(dest), payload) is True
    assert json.loads(dest.read_text()) == payload
    assert sorted(p.name for p in tmp_path.iterdir()) == ["result.json"]  # no .part left behind


def test_diagnose_says_when_its_candidates_are_already_in_the_model(capsys, monkeypatch):
    """--candidates that --effects already holds: nothing to try is an input error
    (not a silent 'verdict: none'), and one of several is named as not tried."""
    import app.core.diagnose

    def must_not_run(*a, **k):
        raise AssertionError("the run started")

    monkeypatch.setattr(app.core.diagnose, "diagnose", must_not_run)
    demo = str(ROOT / "resources" / "demo")
    assert main(["diagnose", demo, "--effects", "viscoelastic", "--candidates", "viscoelastic"]) == 2
    err = capsys.readouterr().err
    assert "--candidates: viscoelastic already in the current model" in err and "nothing to try" in err
    every = "hyperelastic,viscoelastic,sliding-bottom,probe-slip,compressibility,inclusion"
    assert main(["diagnose", demo, "--effects", every]) == 2
    assert "every effect already in the current model" in capsys.readouterr().err
    with pytest.raises(AssertionError, match="the run started"):  # one left to try: the run goes on
        main(["diagnose", demo, "--effects", "viscoelastic", "--candidates", "viscoelastic,probe-slip"])
    assert "viscoelastic already in the current model, not tried" in capsys.readouterr().err


def test_diagnose_no_confirm_turns_the_finer_mesh_confirmation_off(monkeypatch):
    """--no-confirm: a finding on a thin margin stays the verdict without the finer
    mesh's diagnosis (app.core.diagnose.diagnose(confirm=False)); by default it is confirmed."""
    import app.core.diagnose

    asked = []

    class Stop(Exception):
        pass

    def stop(*a, **k):
        asked.append(k["confirm"])
        raise Stop  # enough: the call's arguments are what is tested

    monkeypatch.setattr(app.core.diagnose, "diagnose", stop)
    demo = str(ROOT / "resources" / "demo")
    for extra in ([], ["--no-confirm"]):
        with pytest.raises(Stop):
            main(["diagnose", demo, "--candidates", "probe-slip", "--quiet", *extra])
    assert asked == [True, False]


@pytest.mark.parametrize("command", ["identify", "diagnose"])
@pytest.mark.parametrize("options,words", [
    (["--inclusion-at", "58,45,83,6"], "give --effects inclusion"),
    (["--effects", "inclusion", "--inclusion-at", "58,45,83"], "expected 4 numbers"),
    (["--effects", "inclusion", "--inclusion-at", "58,45,100,6"], "the centre (58, 45, 100) mm is outside the "
                                                                  "specimen (90 x 90 x 96 mm"),
    (["--effects", "inclusion", "--inclusion-at", "58,45,83,0"], "the radius must be positive"),
])
def test_inclusion_at_refuses_a_sphere_it_cannot_place_before_the_run(capsys, monkeypatch, command, options, words):
    """--inclusion-at gives the current model's sphere instead of locating it:
    a malformed one is refused, naming the option, before anything is located,
    meshed or fitted."""
    import app.core.diagnose

    def must_not_run(*a, **k):
        raise AssertionError("the run started")

    for name in ("diagnose", "locate_inclusion", "current_model"):
        monkeypatch.setattr(app.core.diagnose, name, must_not_run)
    assert main([command, str(ROOT / "resources" / "demo"), *options, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("elastoid: --inclusion-at") and words in err and "Traceback" not in err, err


def test_diagnose_keeps_the_placed_inclusion_for_the_next_step(capsys, monkeypatch):
    """A diagnosis whose verdict is an inclusion identifies it where the
    identification places it; `diagnose --effects inclusion` without more
    locates it from the misfit again. On incl-view+52000 (a 60 kPa sphere of
    radius 6 at (58, 45, 84) mm) the verdict's sphere was placed at (58.4, 45,
    83.4) r 5.79 with E_I 55.2 kPa, and the next diagnosis, located anew at
    (57.5, 45, 81.6) r 5.4, identified E_I 79.8 kPa (62.2 with the placed
    sphere given). So the report prints the placed sphere as the next step's
    --inclusion-at, and that option hands it to the diagnosis instead of the
    locator."""
    import app.core.diagnose as dg

    mis = {"chi2": 1000.0, "force_rms_N": 0.02, "displacement_rms_px": 0.86}
    base = dg.Candidate("", (), {"E_B_kPa": 17.9, "E_A_kPa": 64.0}, {}, mis)
    located = {"name": "I", "center_mm": [57.5, 45.0, 81.6], "radius_mm": 5.4}
    incl = dg.Candidate("inclusion", ("inclusion",), {"E_B_kPa": 17.9, "E_A_kPa": 63.2, "E_I_kPa": 55.0}, {},
                        {**mis, "displacement_rms_px": 0.49}, 3, 751.4, "a region deforms less",
                        inclusion=located, material=True)
    placed = {"name": "I", "center_mm": [58.4, 45.0, 83.4], "radius_mm": 5.791}
    identified = {"parameters": {"E_B_kPa": 17.89, "E_A_kPa": 63.15, "E_I_kPa": 55.16}, "cost": {"total": -1.05},
                  "seconds": 60.0, "inclusion": placed}
    incl.identified = identified
    asked = []

    def diagnosed(exp, **k):
        asked.append(k["inclusion"])
        return dg.Diagnosis(str(exp.path), base, [incl], "inclusion", dg.NoiseModel(0.0191, 1481, 0.134, 240), 1.0)

    def must_not_locate(*a, **k):
        raise AssertionError("located again")

    monkeypatch.setattr(dg, "diagnose", diagnosed)
    monkeypatch.setattr(dg, "locate_inclusion", must_not_locate)
    demo = str(ROOT / "resources" / "demo")
    assert main(["diagnose", demo]) == 0
    out = capsys.readouterr().out
    assert ("  next: add it with --effects inclusion --inclusion-at 58.4,45,83.4,5.79, for identify or the next "
            "diagnose") in out, out
    # that step: the sphere given, not located; the current model's inclusion named as a new region would be
    assert main(["diagnose", demo, "--effects", "inclusion", "--inclusion-at", "58.4,45,83.4,5.79"]) == 0
    assert asked[-1] == {"name": "I", "center_mm": [58.4, 45.0, 83.4], "radius_mm": 5.79}
    # where the identification did not move the sphere, the located one is printed
    identified.pop("inclusion")
    assert main(["diagnose", demo]) == 0
    assert "--effects inclusion --inclusion-at 57.5,45,81.6,5.4," in capsys.readouterr().out


def test_diagnose_refuses_a_malformed_memory_cap_before_the_run(capsys, monkeypatch):
    """ELASTOID_MEMORY_GB is read only when memory gets short, minutes into a
    diagnosis: a value that is not a number is refused before anything runs."""
    import app.core.diagnose

    def must_not_run(*a, **k):
        raise AssertionError("the run started")

    monkeypatch.setattr(app.core.diagnose, "diagnose", must_not_run)
    monkeypatch.setenv("ELASTOID_MEMORY_GB", "8GB")
    assert main(["diagnose", str(ROOT / "resources" / "demo"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "ELASTOID_MEMORY_GB must be a positive number of gigabytes, not '8GB'" in err and "Traceback" not in err


def test_identify_locates_the_inclusion_and_refines_it_when_asked(tmp_path_factory, monkeypatch, capsys):
    """`identify --effects inclusion` used to fit the model without any inclusion
    and call it one. Now the inclusion is located from the misfit as a diagnosis
    does, meshed as a new region and fitted: its modulus, centre and radius are
    parameters of the JSON. The hidden-inclusion case (seed 13: a 4 mm sphere of
    60 kPa in 15 kPa tissue), on the tests' identification mesh, whose located
    sphere's mesh is committed.

    With `--refine-inclusion` the located sphere's
    place and size are searched as the Model check's refinement does, and the fit
    uses a refined sphere only when it is shown to fit the measurements better;
    the JSON says which, and why. Seed 13's hidden sphere, on the tests'
    identification mesh (the located sphere's mesh committed): located at (24.7,
    20, 13.8) r 4.5, 1.3 mm from the truth; the search's best, (25.3, 20, 14.4) r
    3.9, fits only 2.9% better, under what a new mesh moves, so the located
    sphere is kept and nothing new is meshed (measured 2026-11-29: when it was
    used, E_A came out 41.3 kPa instead of 43.6, the truth 45). About a minute.
    Which outcome the batch takes when the refinement is used is tested in
    tests/core/test_diagnose.py, with the Model check's steps stubbed. Since the
    located sphere is kept, the fit is the one `--effects inclusion` alone makes
    (that run was a test of its own, 30 s, until 2026-12-01)."""
    from app import cli
    from app.core.simulate import read_truth
    from tests.core import synthetic

    from app.core import diagnose as diagnose_module

    monkeypatch.setattr(cli, "_mesh_settings", lambda args, exp: synthetic.DIAGNOSE_ID_MESH)
    # the search's first round (six trials: each direction once); its full search is tested in
    # tests/core/test_diagnose.py, and a shorter search finds less, so the located sphere is kept all the more
    monkeypatch.setattr(diagnose_module, "REFINE_MAX_TRIALS", 6)
    exp = synthetic.diagnose_experiment(tmp_path_factory, "inclusion")
    truth = read_truth(exp.path)
    dest = exp.path.parent / "result.json"
    assert main(["identify", str(exp.path), "--effects", "inclusion", "--refine-inclusion", "--starts", "10,30",
                 "--json", str(dest), "--quiet"]) == 0
    result = json.loads(dest.read_text())
    inc, printed = result["inclusion"], capsys.readouterr().out
    ref = inc["refinement"]
    assert set(ref) == {"refined", "located_center_mm", "located_radius_mm", "chi2_located", "chi2_refined",
                        "note", "seconds"}, ref
    assert not ref["refined"] and ref["chi2_refined"] is None and ref["seconds"] > 0, ref
    assert ref["note"].startswith("the located sphere is kept: the inclusion already sits about where it fits "
                                  "best"), ref
    assert inc["center_mm"] == ref["located_center_mm"] and inc["radius_mm"] == ref["located_radius_mm"]
    assert np.linalg.norm(np.subtract(inc["center_mm"], truth["hidden_regions"][0]["center_mm"])) < 1.5, inc
    p = result["parameters"]
    assert p["center_mm"] == inc["center_mm"] and p["radius_mm"] == inc["radius_mm"]
    for region in ("B", "A"):
        assert p[f"E_{region}_kPa"] == pytest.approx(truth["moduli_kPa"][region], rel=0.05), p
    assert re.search(r"\n  not refined in \d+\.\d s; the located sphere is kept: ", printed), printed
    # the located inclusion, as `--effects inclusion` alone reports it
    assert result["effects"] == ["inclusion"]
    assert f"inclusion {inc['name']} (not in the experiment, located from the misfit in " in printed
    # the fit's seconds leave the locating out, so it has its own figure
    said = re.search(r"located from the misfit in (\d+\.\d) s before the fit\): centre", printed)
    assert said and inc["locate_seconds"] > 0, printed
    assert float(said.group(1)) == pytest.approx(inc["locate_seconds"], abs=0.051)  # printed to 0.1 s, kept to 0.01
    assert f"E_{inc['name']}_kPa =" in printed
    assert set(p) == {"E_B_kPa", "E_A_kPa", f"E_{inc['name']}_kPa", "center_mm", "radius_mm"}
    assert p[f"E_{inc['name']}_kPa"] > 2.0 * p["E_B_kPa"], p  # stiffer than its tissue, as the truth's


@pytest.mark.parametrize("options,option,words", [
    (["--depth-mm", "200"], "--depth-mm", "96 mm high"),
    (["--depth-mm", "-3"], "--depth-mm", "must be positive"),
    (["--frames-at", "0,20"], "--frames-at", "between 0 and the depth"),
    (["--frames-at", "5,2"], "--frames-at", "must increase"),
    (["--frames-at", "0"], "--frames-at", "at least one deformed frame"),
    (["--noise-N", "-1"], "--noise-N", "zero or positive"),
    (["--rows", "0"], "--rows/--cols", "32 x 32 pixels"),
    (["--nu", "0.5"], "--nu", "between -1 and 0.5"),
    (["--size-mm", "0,10,10"], "--size-mm", "must be positive"),
    (["--face-mm", "200,10"], "--face-mm", "does not lie on the"),
    (["--probe-center-mm", "3,45"], "--probe-center-mm", "does not lie on the"),
    (["--probe-center-mm", "3"], "--probe-center-mm", "expected 2 numbers"),
    (["--probe-center-mm", "45,8", "--probe-turn-deg", "270"], "--probe-center-mm", "does not lie on the"),
    (["--hold-s", "-1"], "--hold-s", "zero or positive"),
    (["--effects", "viscoelastic", "--g1", "1.5"], "--g1", "[0, 1)"),
    (["--moduli", "B=-3,A=5"], "--moduli", "region 'B' must be positive"),
    (["--inclusion", "sphere:45,45,90,15"], "--inclusion", "reaches outside"),
    (["--hidden", "sphere:45,45,95,5,60"], "--hidden", "reaches outside"),
    (["--size-mm", "a"], "--size-mm", "expected comma-separated numbers, got 'a'"),  # tracebacks, these two
    (["--moduli", "B=x"], "--moduli", "expected NAME=kPa pairs"),
])
def test_simulate_refuses_what_cannot_be_simulated_before_meshing(tmp_path, capsys, monkeypatch, options, option,
                                                                   words):
    """Each of these once went on to mesh (or failed later with a traceback): now
    the message names the option, nothing is meshed and no folder is written."""
    import app.core.simulate

    def must_not_mesh(*a, **k):
        raise AssertionError("meshing started")

    monkeypatch.setattr(app.core.simulate.SpecimenTwin, "build", must_not_mesh)
    out = tmp_path / "exp"
    assert main(["simulate", str(out), *options, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"elastoid: {option}: ") and words in err and "Traceback" not in err, err
    assert not out.exists()


@pytest.mark.parametrize("make,words", [
    (lambda out: (out.mkdir(), (out / "keep.txt").write_text("old")), "already exists and is not empty"),
    (lambda out: out.write_text("a file"), "is a file, not a folder"),
])
def test_simulate_refuses_an_occupied_output_before_meshing(tmp_path, capsys, monkeypatch, make, words):
    """The output was checked only when the experiment was written, after the
    truth had been meshed and solved (102 s at the default size)."""
    import app.core.simulate

    def must_not_mesh(*a, **k):
        raise AssertionError("meshing started")

    monkeypatch.setattr(app.core.simulate.SpecimenTwin, "build", must_not_mesh)
    out = tmp_path / "exp"
    make(out)
    before = sorted(p.name for p in tmp_path.rglob("*"))
    assert main(["simulate", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"elastoid: {out}: ") and words in err and "Traceback" not in err, err
    assert sorted(p.name for p in tmp_path.rglob("*")) == before  # nothing written, nothing lost


@pytest.mark.parametrize("options,words", [
    (["--frames", "0,7"], "--frames: there is no frame 7: the experiment has 3 frames, 0 to 2"),
    (["--frames", "1,1"], "--frames: frame 1 is given twice"),
    (["--frames", "a"], "argument --frames: expected comma-separated frame indices"),
    (["--starts", "0,-5"], "--starts: start moduli must be positive"),
    (["--nu", "0.5"], "argument --nu: Poisson's ratio must lie between -1 and 0.5"),
    (["--mesh-edge-mm", "0"], "argument --mesh-edge-mm: must be positive"),
    # these ended in tracebacks, or (the 2 x 2 px ROI) ran and reported E_A 27 kPa for 63 as "ok"
    (["--starts", "a"], "elastoid: --starts: expected comma-separated numbers, got 'a'"),
    (["--roi", "a,b"], "argument --roi: expected four whole numbers col0,row0,col1,row1, got 'a,b'"),
    (["--roi", "50,50,40,40"], "--roi: [50, 50, 40, 40] is empty"),
    (["--roi", "0,0,1000,1000"], "--roi: [0, 0, 1000, 1000] reaches outside the 200 x 256 px images"),
    (["--roi", "10,10,12,12"], "--roi: [10, 10, 12, 12] is 2 x 2 px; the comparison needs at least 32 x 32 px"),
    (["--roi", "10,10,12,12", "--effects", "viscoelastic"], "is 2 x 2 px"),
    (["--refine-inclusion"], "--refine-inclusion refines the inclusion effect's sphere: give --effects inclusion"),
    (["--effects", "inclusion", "--refine-inclusion", "--frames", "0,2"],
     "--refine-inclusion works on the experiment's ROI and frames, as the Model check does: leave out --roi"),
])
def test_identify_refuses_bad_options_before_the_run(capsys, monkeypatch, options, words):
    """--frames 0,7 on three frames silently used frame 1 (the index wrapped), 1,1
    compared a frame with itself, and --starts 0 or --nu 0.5 ended in a traceback."""
    import app.core.effects.model
    import app.core.identify

    for cls in (app.core.identify.Problem, app.core.effects.model.EffectProblem):
        monkeypatch.setattr(cls, "from_experiment",
                            classmethod(lambda *a, **k: (_ for _ in ()).throw(AssertionError("the run started"))))
    try:
        code = main(["identify", str(ROOT / "resources" / "demo"), *options, "--quiet"])
    except SystemExit as exc:  # argparse's own refusals
        code = exc.code
    assert code == 2
    err = capsys.readouterr().err
    assert words in err and "Traceback" not in err, err


def test_frames_may_count_from_the_end():
    from app.core.experiment import read_experiment
    from app.core.identify import frame_indices

    exp = read_experiment(ROOT / "resources" / "demo")
    assert frame_indices(exp) == (0, 1, 2)
    assert frame_indices(exp, [0, -1]) == (0, 2)
    with pytest.raises(Exception, match="no frame -4"):
        frame_indices(exp, [0, -4])


def test_identify_and_diagnose_say_when_the_default_frames_leave_some_out(capsys):
    """More than MAX_DEFAULT_FRAMES deeper frames (a scanner at video rate): the
    commands compare a spread of them, and say so on stderr unless --quiet; frames
    the user gives, or few enough, say nothing."""
    from types import SimpleNamespace

    from app.cli import _say_thinned

    video = SimpleNamespace(frames=[SimpleNamespace(displacement_mm=0.1 * i) for i in range(80)])
    _say_thinned(video, None, quiet=False)
    assert capsys.readouterr().err.startswith("elastoid: comparing 30 of the 79 frames deeper than frame 0, spread")
    _say_thinned(video, None, quiet=True)
    _say_thinned(video, (0, 5, 9), quiet=False)
    _say_thinned(SimpleNamespace(frames=video.frames[:31]), None, quiet=False)
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("command", ["identify", "diagnose"])
def test_the_element_size_options_set_the_mesh_and_keep_the_automatic_rest(command):
    """--outline-edge-mm (the size along the probe face's outline) alone keeps the
    automatic sizes elsewhere, and another size option keeps the automatic
    outline (1.0 mm); with no size option the sizes stay automatic. --region-scale
    refines the regions' automatic sizes alone."""
    from dataclasses import replace

    from app import cli
    from app.core.experiment import read_experiment
    from app.core.mesh import auto_settings, region_edge_mm

    exp = read_experiment(ROOT / "resources" / "demo")
    auto = auto_settings(exp.specimen.size_mm, exp.probe.face_rect_mm(), exp.specimen.regions)
    parse = cli.build_parser().parse_args
    assert cli._mesh_settings(parse([command, "resources/demo"]), exp) is None
    s = cli._mesh_settings(parse([command, "resources/demo", "--outline-edge-mm", "0.8"]), exp)
    assert (s.edge_mm, s.probe_edge_mm, s.outline_edge_mm) == (auto.edge_mm, auto.probe_edge_mm, 0.8)
    s = cli._mesh_settings(parse([command, "resources/demo", "--probe-edge-mm", "1.5"]), exp)
    assert (s.edge_mm, s.probe_edge_mm, s.outline_edge_mm) == (auto.edge_mm, 1.5, 1.0) == (10.0, 1.5, auto.outline_edge_mm)
    # --region-scale: the regions' automatic sizes (a located inclusion's too) times the factor, the rest automatic
    s = cli._mesh_settings(parse([command, "resources/demo", "--region-scale", "0.5"]), exp)
    assert s == replace(auto, region_scale=0.5)
    a = exp.specimen.regions[1]
    assert region_edge_mm(a, s) == pytest.approx(0.5 * region_edge_mm(a, auto))
    with pytest.raises(SystemExit):
        parse([command, "resources/demo", "--region-scale", "0"])


def test_the_mesh_check_identifies_the_result_again_on_a_finer_mesh(tmp_path, capsys):
    """identify --mesh-check: the same model on a finer mesh, identified from the
    optimum. On a committed test phantom (nothing hidden; truth B 15, A 45 kPa;
    both meshes committed, the finer one not the truth's), the finer mesh has more
    vertices, its moduli are within 10% of the truth, and the changes printed and
    in the JSON are the two identifications' ratios."""
    dest = tmp_path / "r.json"
    assert main(["identify", str(ROOT / "tests" / "data" / "experiments" / "diagnose" / "none-5"), "--starts",
                 "10,30", "--mesh-check", "--json", str(dest), "--quiet"]) == 0
    printed = capsys.readouterr().out
    result = json.loads(dest.read_text())
    check = result["mesh_check"]
    assert check["scale"] == 0.7
    coarse, fine = check["nodes"]
    assert fine > 2 * coarse, check["nodes"]
    assert set(check["parameters"]) == set(check["change"]) == {"E_B_kPa", "E_A_kPa"}
    for name, truth in (("E_B_kPa", 15.0), ("E_A_kPa", 45.0)):
        assert check["parameters"][name] == pytest.approx(truth, rel=0.10), check
        assert check["change"][name] == pytest.approx(check["parameters"][name] / result["parameters"][name] - 1,
                                                      abs=1e-12)
    assert f"mesh check: on a mesh 0.7 times the size ({fine:,} vertices against {coarse:,}" in printed, printed
    assert f"E_A {check['parameters']['E_A_kPa']:.2f} kPa ({check['change']['E_A_kPa']:+.1%})" in printed, printed
    assert "than their standard error from the data" in printed or "than its standard error" in printed, printed


def test_the_mesh_check_keeps_fixed_moduli_fixed_and_the_image_only_level(monkeypatch):
    """A modulus the identification held fixed stays at its value on the finer
    mesh; with the image-only cost (NMI) and nothing fixed the moduli's level is
    not identifiable, so the first modulus stays and the ratios are searched, as
    the identification does (the model and the fit stubbed: which parameters the
    finer mesh's fit searches)."""
    from types import SimpleNamespace

    import app.core.diagnose as dg
    from app.core.experiment import read_experiment
    from app.core.mesh_check import mesh_check

    searched = []

    class Finer:
        parameter_names = ("E_B_kPa", "E_A_kPa")
        mesh = SimpleNamespace(n_nodes=6266)

        def __init__(self, cost):
            self.cost_kind = cost

        def release(self):
            pass

    def fit(problem, start, *, cancel=None, free=None):
        searched.append(free)
        return SimpleNamespace(parameters=dict(start), cost={})

    monkeypatch.setattr(dg, "current_model", lambda exp, effects, **kw: Finer(kw.get("cost", "joint")))
    monkeypatch.setattr(dg, "identify_from", fit)
    exp = read_experiment(ROOT / "resources" / "demo")
    params = {"E_B_kPa": 18.0, "E_A_kPa": 63.0}
    for cost, fixed, free in (("joint", (), ("E_B_kPa", "E_A_kPa")), ("joint", ("E_A_kPa",), ("E_B_kPa",)),
                              ("nmi", (), ("E_A_kPa",)), ("nmi", ("E_B_kPa",), ("E_A_kPa",))):
        check = mesh_check(exp, (), params, 2558, fixed=fixed, cost=cost)
        assert searched[-1] == free, (cost, fixed, searched[-1])
        assert check.parameters == params


def test_the_mesh_check_says_which_moduli_the_mesh_limits():
    """A modulus that moves on the finer mesh by more than its standard error from
    the data is limited by the mesh; when none does, the mesh is fine enough."""
    from app.core.mesh_check import MeshCheck

    check = MeshCheck(0.7, (2558, 6266), {"E_B_kPa": 17.73, "E_A_kPa": 62.54},
                      {"E_B_kPa": 17.94, "E_A_kPa": 62.60}, {"total": -1.05}, 101.6)
    assert check.change["E_B_kPa"] == pytest.approx(17.94 / 17.73 - 1)
    lines = check.lines({"E_B_kPa": 0.001, "E_A_kPa": 0.01})
    assert lines[0] == ("mesh check: on a mesh 0.7 times the size (6,266 vertices against 2,558; 102 s): "
                        "E_B 17.94 kPa (+1.2%), E_A 62.60 kPa (+0.1%)")
    assert lines[1].startswith("E_B moved by more than its standard error from the data (0.1%)"), lines
    assert "limits it" in lines[1]
    lines = check.lines({"E_B_kPa": 0.02, "E_A_kPa": float("inf")})
    assert lines[1].startswith("each modulus moved by less than its standard error"), lines
    assert len(check.lines(None)) == 1  # without standard errors, the figures alone
    assert MeshCheck(0.7, (None, 6266), check.before, check.parameters, {}, 1.0).lines()[0].startswith(
        "mesh check: on a mesh 0.7 times the size (6,266 vertices; 1 s)")


def test_diagnose_mesh_check_checks_the_model_the_diagnosis_calls_for(monkeypatch):
    """diagnose --mesh-check checks the identified model: the verdict's effects and
    parameters, and an inclusion at the place the identification found (not the
    located one), without the sphere's other keys."""
    from types import SimpleNamespace

    from app import cli
    from app.core import mesh_check as mc

    seen = {}

    def fake(exp, effects, parameters, nodes, **kw):
        seen.update(effects=effects, parameters=parameters, nodes=nodes, **kw)
        return "checked"

    monkeypatch.setattr(mc, "mesh_check", fake)
    placed = {"name": "I", "center_mm": [55.7, 45.0, 76.2], "radius_mm": 4.7}
    located = {"name": "I", "center_mm": [57.5, 45.0, 78.0], "radius_mm": 5.4, "meshed_at": None}
    cand = SimpleNamespace(inclusion=located, problem=SimpleNamespace(mesh=SimpleNamespace(n_nodes=3465)))
    result = SimpleNamespace(identified={"effects": ["inclusion"], "parameters": {"E_I_kPa": 79.1},
                                         "inclusion": {**placed, "meshed_at": located}},
                             verdict="inclusion", baseline=None, candidate=lambda e: cand)
    args = cli.build_parser().parse_args(["diagnose", "x", "--mesh-check", "--quiet"])
    assert cli._diagnosis_mesh_check(args, "exp", result, None, None) == "checked"
    assert seen["effects"] == ["inclusion"] and seen["parameters"] == {"E_I_kPa": 79.1}
    assert seen["inclusion"] == placed and seen["nodes"] == 3465
    from app.core.errors import MeshingError

    def failing(*a, **kw):
        raise MeshingError("fTetWild gave up")

    monkeypatch.setattr(mc, "mesh_check", failing)  # the diagnosis stands without its check
    assert cli._diagnosis_mesh_check(args, "exp", result, None, None) is None
    result.identified = None
    assert cli._diagnosis_mesh_check(args, "exp", result, None, None) is None


def test_a_failed_mesh_check_loses_nothing(tmp_path, capsys, monkeypatch):
    """When the finer mesh cannot be made (here the mesher fails), identify --mesh-check
    still writes and prints the identification, and says on stderr what failed."""
    from app.core import mesh_check as mc
    from app.core.errors import MeshingError

    def failing(*a, **kw):
        raise MeshingError("fTetWild gave up")

    monkeypatch.setattr(mc, "mesh_check", failing)
    dest = tmp_path / "r.json"
    assert main(["identify", str(ROOT / "tests" / "data" / "experiments" / "diagnose" / "none-5"), "--starts",
                 "10,30", "--mesh-check", "--json", str(dest), "--quiet"]) == 0
    out = capsys.readouterr()
    result = json.loads(dest.read_text())
    assert set(result["parameters"]) == {"E_B_kPa", "E_A_kPa"} and "mesh_check" not in result
    assert "E_A_kPa =" in out.out and "mesh check:" not in out.out
    assert "--mesh-check failed: fTetWild gave up" in out.err, out.err
