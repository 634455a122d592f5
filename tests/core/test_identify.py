"""Identification on synthetic experiments made by the ultrasound simulator on a
finer mesh, with noise: several seeds and geometries."""

import threading

import numpy as np
import pytest

from app.core.errors import Cancelled
from app.core.experiment import read_experiment
from app.core.identify import Problem, identify
from app.core.simulate import read_truth
from tests.core import synthetic

CASES = synthetic.COMMITTED_CASES
# The experiments and their identification meshes are committed
# (tests/data/experiments, tests/data/meshes): fTetWild is not deterministic, so
# fresh meshes made every CI run a different problem (once the six starts of
# seed 2 split 3 and 3 between optima 3% apart). Measured on these experiments
# and meshes (bench/identify_committed.py, 2026-11-25, probe face meshed along
# its outline in truth and model alike): E_B -1.5%, -1.3%, -1.7%, E_A -1.0%,
# -2.1%, -1.9%; the NMI-only ratio +0.5%, -0.8%, -0.1%. The moduli's common
# -1.5% is the identification mesh being stiffer than the finer truth mesh.
# Before the outline was meshed, fTetWild left 12-20% of the probe face unbonded
# (triangles straddling the outline) and E_A came out up to +5.5%.
TOL = 0.05


@pytest.fixture(scope="module", params=CASES, ids=[f"{g}-seed{s}" for g, s in CASES])
def case(request):
    # the experiments are committed (simulating one takes 50-70 s: a 50k-tet truth
    # mesh and its solve); `python -m tests.core.synthetic` writes them again. The
    # identification meshes come from tests/data/meshes (seeded by tests/conftest.py).
    geometry, seed = request.param
    folder = synthetic.committed(geometry, seed)
    exp = read_experiment(folder)
    joint = Problem.from_experiment(exp, cost="joint")
    nmi = Problem(exp, joint.mesh, joint.fe, joint.rm, nu=0.49, cost="nmi", frames=joint.frames,
                  roi_px=None, force_weight=1.0, bins=joint.bins)
    return read_truth(folder)["moduli_kPa"], joint, nmi


def test_joint_cost_recovers_every_modulus_within_5_percent(case):
    truth_kPa, joint, _ = case
    result = identify(joint)  # the paper's six starts
    for region, truth in truth_kPa.items():
        got = result.parameters[f"E_{region}_kPa"]
        assert abs(got / truth - 1) < TOL, (region, got, truth)
    # most starts reach the chosen optimum (with hard bins and no restarts they
    # stopped up to 4% apart; an occasional start still ends in another valley)
    best = result.parameters["E_A_kPa"] / result.parameters["E_B_kPa"]
    ratios = [st["parameters"]["E_A_kPa"] / st["parameters"]["E_B_kPa"] for st in result.starts]
    assert sum(abs(r / best - 1) < 0.01 for r in ratios) >= 4, ratios
    ident = result.identifiability
    assert all(flag == "ok" for flag in ident.flags.values()), ident.lines()
    # standard errors from the data (jackknife over blocks of the ROI): finite, wider
    # than the 0.25 px noise model's for the inclusion (that model takes every control
    # point as an independent measurement), and the estimate within reach of them
    # plus the mesh's own bias of about 2% (bench/identifiability_calibration.py
    # checks them against the scatter over speckle seeds)
    data = ident.standard_error_rel_data
    assert all(np.isfinite(v) and v > 0 for v in data.values()), ident.lines()
    assert data["E_A_kPa"] > ident.standard_error_rel["E_A_kPa"], ident.lines()
    r_se = ident.ratio_standard_error_rel_data["E_A_kPa/E_B_kPa"]
    assert 0.002 < r_se < 0.1, ident.lines()
    assert abs(best / (truth_kPa["A"] / truth_kPa["B"]) - 1) < 4 * r_se + 0.02, (best, ident.lines())


def test_nmi_cost_recovers_the_ratio_but_not_the_level(case):
    truth_kPa, _, nmi = case
    result = identify(nmi)  # the paper's six starts
    p = result.parameters
    ratio, truth = p["E_A_kPa"] / p["E_B_kPa"], truth_kPa["A"] / truth_kPa["B"]
    assert abs(ratio / truth - 1) < TOL, (ratio, truth)
    # the identifiability report says why the level is not found
    ident = result.identifiability
    assert all(f.startswith("unconstrained") for f in ident.flags.values())
    assert any("overall stiffness level" in line for line in ident.lines())
    # from the data too: each modulus undetermined, their ratio determined
    assert all(not np.isfinite(v) for v in ident.standard_error_rel_data.values()), ident.lines()
    assert 0.002 < ident.ratio_standard_error_rel_data["E_A_kPa/E_B_kPa"] < 0.1, ident.lines()


def test_a_point_that_is_not_a_minimum_is_reported_as_one(case, monkeypatch):
    """Where a fit of a model the data do not follow stops on a compromise, the cost
    can still fall along some direction (a saddle): the sandwich has no curvature to
    invert there. The report says so, names the direction, and keeps the standard
    error of the modulus the cost does settle. The cost is replaced by a saddle in
    log-moduli, falling along E_A, with a jackknife scatter per group of blocks."""
    _, joint, _ = case
    params = {"E_B_kPa": 18.0, "E_A_kPa": 63.0}
    names = joint.parameter_names
    x0 = np.log(joint.theta(joint.complete(params)))
    b, a = names.index("E_B_kPa"), names.index("E_A_kPa")
    tilts = np.random.default_rng(0).normal(scale=0.05, size=(16, len(x0)))

    def saddle(x):
        d = np.asarray(x) - x0
        image = 2.0 * d[b] ** 2 - 0.5 * d[a] ** 2
        return image, image + tilts @ d, 0.0, np.zeros(len(joint.log_F))

    monkeypatch.setattr(joint, "_cost_parts", saddle)
    ident = joint.identifiability(params)
    data = ident.standard_error_rel_data
    assert np.isfinite(data["E_B_kPa"]) and data["E_B_kPa"] > 0, ident.lines()
    assert not np.isfinite(data["E_A_kPa"]), ident.lines()
    assert ident.flags["E_A_kPa"].startswith("not at a minimum of the cost"), ident.flags
    assert not ident.flags["E_B_kPa"].startswith("not at a minimum"), ident.flags
    (v,) = ident.falling_directions
    assert abs(abs(v[a]) - 1) < 1e-6 and abs(v[b]) < 1e-6, v
    said = [line for line in ident.lines() if line.startswith("the cost still falls when the log-moduli move")]
    assert len(said) == 1 and "E_A_kPa" in said[0] and "E_B_kPa" not in said[0], said
    assert ident.to_dict()["falling_directions"] == ident.falling_directions


def test_a_small_standard_error_is_printed_as_small_not_as_zero():
    """One decimal of a percent, except under 0.1%: the demo's E_B, fixed by the force
    to 0.024% under the noise model, printed as "+/-0.0%" read as no error at all."""
    from app.core.identify import Identifiability, percent_text

    assert [percent_text(x) for x in (0.00013, 0.0009, 0.01, 0.25, 0.0)] == ["0.013%", "0.09%", "1.0%", "25.0%", "0.0%"]
    ident = Identifiability(("E_B_kPa",), {"E_B_kPa": 0.00013}, np.eye(1), {"E_B_kPa": "ok"}, {"E_B_kPa": 0.66},
                            {"E_B_kPa": 0.86}, [], "a noise model", {"E_B_kPa": 0.001}, {})
    assert any(line.startswith("E_B_kPa: +/-0.1% from the data (+/-0.013% from the noise model)")
               for line in ident.lines()), ident.lines()


def test_images_alone_fix_only_ratios(case):
    """Displacement control: scaling every modulus leaves the warp and NMI unchanged,
    while the force scales with them."""
    _, joint, _ = case
    p = {"E_B_kPa": 12.0, "E_A_kPa": 30.0}
    q = {k: 2.5 * v for k, v in p.items()}
    cp, cq = joint.evaluate(p), joint.evaluate(q)
    assert cp["nmi"] == pytest.approx(cq["nmi"], abs=1e-12)
    assert np.allclose(joint.model_force_N(q), 2.5 * joint.model_force_N(p))


def test_progress_reports_every_evaluation_and_cancel_stops(case):
    _, joint, _ = case
    seen = []
    cancel = threading.Event()

    def progress(rep):
        seen.append(rep)
        if len(seen) == 15:
            cancel.set()

    with pytest.raises(Cancelled):
        identify(joint, (10.0, 30.0), progress=progress, cancel=cancel)
    assert len(seen) == 15
    assert [r.evaluation for r in seen] == list(range(1, 16))
    assert set(seen[0].cost) == {"total", "nmi", "force_rms_N"}
    assert set(seen[0].parameters) == set(joint.parameter_names)


def test_the_frame_pairs_and_the_models_of_an_experiment_share_one_warp(case):
    """Every pair warps the same source frame with the same control points: one
    FastWarp serves them all, and every model of the experiment and ROI (a diagnosis
    holds seven or eight). One per pair took 0.94 GB per model with 30 frame pairs
    at paper size, and a diagnosis of that experiment peaked at 19 GB."""
    _, joint, nmi = case
    assert len(joint.pairs) >= 2
    assert all(p.warp is joint.pairs[0].warp for p in (*joint.pairs, *nmi.pairs))
    # the precomposed field is shared as well, and scaled by each pair's own travel
    a = joint.rm.coords(joint.theta({"E_B_kPa": 14.0, "E_A_kPa": 40.0}))
    for pair in joint.pairs:
        vals = joint.control_displacement_px(a, pair)
        np.testing.assert_allclose(joint._coarse_field(pair, a), pair.warp.forward_coarse(vals), atol=1e-9)
    assert len({k for k in joint._G if k[1] == joint.rm.k}) == 1


def test_the_papers_hard_binned_cost_equals_skimage(case):
    """similarity="hard" is the paper's estimator: the cost's NMI is skimage's on
    the warped source and the frame (same bins), averaged over the frame pairs."""
    from skimage.metrics import normalized_mutual_information as sk_nmi

    _, joint, _ = case
    hard = Problem(joint.exp, joint.mesh, joint.fe, joint.rm, nu=0.49, cost="joint", frames=joint.frames,
                   roi_px=None, force_weight=1.0, bins=joint.bins, similarity="hard")
    p = {"E_B_kPa": 14.0, "E_A_kPa": 40.0}
    expected = []
    for pair in hard.pairs:
        w, target, _, mask = hard.warped_source(p, pair.target)
        expected.append(sk_nmi(target[mask], w[mask], bins=hard.bins))
    assert hard.evaluate(p)["nmi"] == pytest.approx(np.mean(expected), abs=1e-9)
    # the smooth estimator of the default cost is close to it
    assert joint.evaluate(p)["nmi"] == pytest.approx(np.mean(expected), rel=0.05)


def test_frames_at_video_rate_are_thinned_to_a_spread_of_them_by_default():
    """later_frames(): a scanner recording at video rate gives hundreds of frames,
    and every frame costs time and memory (31 at paper size: a diagnosis 3.3 min
    and 6.1 GB). By default at most MAX_DEFAULT_FRAMES are compared, spread evenly
    along the probe's path (loading and unloading; a hold's frames see one field
    and would crowd out the rest if spread in time), the deepest always among
    them; fewer are all compared, and frames given by the user are never thinned."""
    from types import SimpleNamespace

    from app.core.identify import MAX_DEFAULT_FRAMES, frame_indices, later_frames, thinned_note

    def exp(travels):
        return SimpleNamespace(frames=[SimpleNamespace(displacement_mm=float(d)) for d in travels])

    few = exp([0.0, 2.5, 5.0, 5.0, 1.0])
    assert frame_indices(few) == (0, 1, 2, 3, 4) and thinned_note(few, frame_indices(few)) == ""
    # 10 frames a second: a 14.8 mm ramp at 1 mm/s, a 60 s hold, the unloading
    ramp = np.round(np.arange(0, 14.85, 0.1), 3)
    video = exp([*ramp, *[14.8] * 600, *ramp[::-1][1:]])
    d = np.array([f.displacement_mm for f in video.frames])
    got = frame_indices(video)
    assert len(got) == MAX_DEFAULT_FRAMES and got[0] == 0 and int(np.argmax(d)) in got
    assert list(got) == sorted(set(got))
    loading, hold, unloading = (sum(lo <= i < hi for i in got[1:]) for lo, hi in ((1, 148), (148, 749), (749, 900)))
    assert hold <= 2 and abs(loading - unloading) <= 2, (loading, hold, unloading)
    assert np.diff(d[list(got[1:loading + 1])]).max() < 2 * 14.8 / 15  # the loading's travels evenly covered
    assert thinned_note(video, got).startswith(f"comparing {MAX_DEFAULT_FRAMES - 1} of the {len(video.frames) - 2} ")
    assert 300 in later_frames(video, keep=(300,)) and 0 not in later_frames(video, source=5)
    assert len(frame_indices(video, list(range(60)))) == 60  # the user's choice stands
    # every frame at one travel (a hold alone): spread over the recording
    held = frame_indices(exp([0.0, *[5.0] * 100]))
    assert len(held) == MAX_DEFAULT_FRAMES and held[1] == 1 and held[-1] == 100
