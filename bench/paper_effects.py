"""Hidden effects at paper size, through the command line as a user runs it.

    python bench/paper_effects.py [--out DIR] [--cases visco,slide,...] [--seed-offset N] [--probe-edge-mm X]

For each case, ``elastoid simulate DIR/CASE --seed S ...`` writes the paper's
phantom (90 x 90 x 96 mm, inclusion A of 63 kPa in B of 18 kPa, pressed
14.8 mm; truth on a mesh 0.7 the size of the identification mesh, frames from
the scatterer simulator, noisy force) with one effect hidden in the truth, and
``elastoid diagnose DIR/CASE --json DIR/CASE.json`` diagnoses it with every
candidate. The ``small-``, ``boxed-`` and ``wide-`` cases are other phantoms
(sizes, region A, moduli, travel and frames of their own). An experiment
folder already in DIR is reused (the neo-Hookean truth takes minutes to
simulate). Prints a table: the verdict (and its rival
in a near tie), where the hidden effect ranked and scored, the moduli with it and with the baseline,
how much the error beyond the noise falls with it in the effect's channel
(for the inclusion, against the model on the inclusion's mesh), and the
diagnosis's wall time and peak resident memory. The identification mesh is
the demo's (the same phantom), shipped in resources/meshes; the truth meshes
and the located inclusions' are made anew.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

NINE_FRAMES = ",".join(f"{14.8 * i / 8:.2f}" for i in range(9))
# other phantoms (their identification meshes are made anew): a small block, a
# box-shaped region A, and a wide block recorded with five frames
SMALL = ["--size-mm", "60,60,50", "--inclusion", "sphere:30,30,30,8", "--moduli", "B=10,A=40", "--depth-mm", "6",
         "--frames-at", "0,3,6"]
BOXED = ["--size-mm", "80,80,60", "--inclusion", "box:40,40,38,16,16,10", "--moduli", "B=25,A=80", "--depth-mm", "8",
         "--frames-at", "0,4,8"]
WIDE = ["--size-mm", "100,70,80", "--inclusion", "sphere:50,35,55,10", "--moduli", "B=8,A=30", "--depth-mm", "10",
        "--frames-at", "0,2.5,5,7.5,10"]
# name -> (seed, simulate options, the hidden effect's id or "none")
CASES = {
    "none": (106, [], "none"),
    "visco": (101, ["--effects", "viscoelastic", "--hold-s", "6", "--g1", "0.3", "--tau1-s", "2"], "viscoelastic"),
    "slide": (102, ["--effects", "sliding-bottom"], "sliding-bottom"),
    "slip": (103, ["--effects", "probe-slip"], "probe-slip"),
    "nu": (104, ["--nu", "0.4"], "compressibility"),
    "incl": (105, ["--hidden", "sphere:22,45,78,6,60"], "inclusion"),  # centred outside the field of view
    "incl-view": (115, ["--hidden", "sphere:58,45,84,6,60"], "inclusion"),  # in view, 12 mm deep, beside A
    "slip-113": (113, ["--effects", "probe-slip"], "probe-slip"),
    "hyper": (107, ["--effects", "hyperelastic"], "hyperelastic"),
    # the simulator's defaults but the effect: no hold, no unloading
    "none-126": (126, [], "none"),
    "visco-ramp": (121, ["--effects", "viscoelastic"], "viscoelastic"),
    "slip-123": (123, ["--effects", "probe-slip"], "probe-slip"),
    "slide-unload": (122, ["--effects", "sliding-bottom", "--hold-s", "3", "--unload"], "sliding-bottom"),
    # nine frames, one every 1.85 mm (2% of the height): what the user guide advises for image effects
    "none-9": (106, ["--frames-at", NINE_FRAMES], "none"),
    "slip-9": (103, ["--effects", "probe-slip", "--frames-at", NINE_FRAMES], "probe-slip"),
    # a frame every half millimetre (31 frames): memory and time with many frames
    "slip-31": (131, ["--effects", "probe-slip", "--frames-at", ",".join(f"{14.8 * i / 30:.3f}" for i in range(31))],
                "probe-slip"),
    # a scanner recording at 5 frames a second: the loading at 1 mm/s (75 frames, 0.2 mm apart), then a 30 s
    # hold (150 more frames, see video_hold): 225 frames, most of them at one travel
    "visco-video": (141, ["--effects", "viscoelastic", "--hold-s", "30", "--g1", "0.3", "--tau1-s", "2",
                          "--frames-at", ",".join(f"{14.8 * i / 74:.3f}" for i in range(75))], "viscoelastic"),
}
CASES.update({
    "small-none": (11, SMALL, "none"),
    "small-none-12": (12, SMALL, "none"),
    "small-slide": (13, [*SMALL, "--effects", "sliding-bottom"], "sliding-bottom"),
    "boxed-none": (21, BOXED, "none"),
    "boxed-slip": (22, [*BOXED, "--effects", "probe-slip"], "probe-slip"),
    "wide-none": (31, WIDE, "none"),
    "wide-nu": (32, [*WIDE, "--nu", "0.4"], "compressibility"),
    # the other effects on these phantoms (added blind, after the rules above were set)
    "small-hyper": (14, [*SMALL, "--effects", "hyperelastic"], "hyperelastic"),
    "boxed-visco": (23, [*BOXED, "--effects", "viscoelastic", "--hold-s", "6", "--g1", "0.3", "--tau1-s", "2"],
                    "viscoelastic"),
    # in view, 14 mm deep, beside A (centres 19 mm apart, radii 10 and 6), 3.75 times stiffer than B
    "wide-incl": (33, [*WIDE, "--hidden", "sphere:34,35,66,6,30"], "inclusion"),
})
# the paper's phantom with what the first sweeps kept fixed varied: the force noise,
# region A softer than B, the probe face, the travel, the image size, weaker effects
# (run blind with --seed-offset 22000, seeds 23001-23036; docs/model-check.md
# "Blind variants of the setup")
CASES.update({
    "lownoise-none": (1001, ["--noise-N", "0.005"], "none"),
    "softA-none": (1002, ["--moduli", "B=18,A=6"], "none"),
    "face-slip": (1003, ["--face-mm", "30,14", "--effects", "probe-slip"], "probe-slip"),
    "noisy-visco": (1004, ["--noise-N", "0.05", "--effects", "viscoelastic", "--hold-s", "10", "--g1", "0.15",
                           "--tau1-s", "5"], "viscoelastic"),
    "nu45": (1005, ["--nu", "0.45"], "compressibility"),
    "slide-10": (1006, ["--effects", "sliding-bottom", "--depth-mm", "10", "--frames-at", "0,5,10"],
                 "sliding-bottom"),
    "soft-sphere": (1007, ["--hidden", "sphere:60,45,84,6,6"], "inclusion"),  # 3 times softer than B, in view
    "bigimg-none": (1008, ["--rows", "400", "--cols", "300"], "none"),
    "lownoise-hyper": (1009, ["--noise-N", "0.005", "--effects", "hyperelastic"], "hyperelastic"),
    "face-none": (1010, ["--face-mm", "30,14"], "none"),
    "face-none-11": (1011, ["--face-mm", "30,14"], "none"),
    "face-slip-12": (1012, ["--face-mm", "30,14", "--effects", "probe-slip"], "probe-slip"),
    "square-none": (1013, ["--face-mm", "20,20", "--depth-mm", "10", "--frames-at", "0,5,10"], "none"),
    "square-slip": (1014, ["--face-mm", "20,20", "--depth-mm", "10", "--frames-at", "0,5,10", "--effects",
                           "probe-slip"], "probe-slip"),
    "deep-none": (1015, ["--depth-mm", "20", "--frames-at", "0,10,20"], "none"),
    "softA-slip": (1016, ["--moduli", "B=18,A=6", "--effects", "probe-slip"], "probe-slip"),
    "face-visco": (1017, ["--face-mm", "30,14", "--effects", "viscoelastic", "--hold-s", "6", "--g1", "0.3",
                          "--tau1-s", "2"], "viscoelastic"),
    "face-slide": (1018, ["--face-mm", "30,14", "--effects", "sliding-bottom"], "sliding-bottom"),
    "face-nu": (1019, ["--face-mm", "30,14", "--nu", "0.4"], "compressibility"),
    "square-nu": (1020, ["--face-mm", "20,20", "--depth-mm", "10", "--frames-at", "0,5,10", "--nu", "0.45"],
                  "compressibility"),
    "noisy-none": (1021, ["--noise-N", "0.05"], "none"),
    "deep-slip": (1022, ["--depth-mm", "20", "--frames-at", "0,10,20", "--effects", "probe-slip"], "probe-slip"),
    "softA-slide": (1023, ["--moduli", "B=18,A=6", "--effects", "sliding-bottom"], "sliding-bottom"),
    "lownoise-slip": (1024, ["--noise-N", "0.005", "--effects", "probe-slip"], "probe-slip"),
    "boxed-square-none": (1025, [*BOXED, "--face-mm", "20,20"], "none"),
    "wide-face-slip": (1026, [*WIDE, "--face-mm", "30,14", "--effects", "probe-slip"], "probe-slip"),
    "small-noisy-nu": (1027, [*SMALL, "--noise-N", "0.05", "--nu", "0.4"], "compressibility"),
    "lowres-none": (1028, ["--rows", "128", "--cols", "100"], "none"),
    "lowres-slide": (1029, ["--rows", "128", "--cols", "100", "--effects", "sliding-bottom"], "sliding-bottom"),
    "shallow-slip": (1030, ["--depth-mm", "5", "--frames-at", "0,2.5,5", "--effects", "probe-slip"], "probe-slip"),
    "homog-none": (1031, ["--inclusion", "none", "--moduli", "B=18"], "none"),
    "homog-slide": (1032, ["--inclusion", "none", "--moduli", "B=18", "--effects", "sliding-bottom"], "sliding-bottom"),
    "boxA-slip": (1033, ["--inclusion", "box:45,45,66,30,30,20", "--effects", "probe-slip"], "probe-slip"),
    "stiff-none": (1034, ["--moduli", "B=60,A=200"], "none"),
    "verysoft-nu": (1035, ["--moduli", "B=3,A=10", "--nu", "0.45"], "compressibility"),
    "stiff-visco": (1036, ["--moduli", "B=60,A=200", "--effects", "viscoelastic", "--hold-s", "6", "--g1", "0.3",
                           "--tau1-s", "2"], "viscoelastic"),
})
HOLD_FPS = {"visco-video": 5.0}  # cases whose hold is recorded at this rate


def video_hold(folder: Path, fps: float, seed: int) -> None:
    """Add the frames a scanner records during the hold, at ``fps``: the simulator
    takes frames during the loading only. Under a held probe the speckle stays
    put (the relaxation changes the force, not the displacement, of this
    one-material relaxation), so each hold frame is the deepest frame with fresh
    electronic noise (2 grey levels). The force of every frame comes from the log."""
    from dataclasses import replace

    import numpy as np

    from app.core.experiment import TOML, experiment_to_toml, read_experiment, write_toml_atomic
    from app.core.images import save_png

    exp = read_experiment(folder)
    last = exp.frames[-1]
    image = exp.image(len(exp.frames) - 1)
    log = exp.force_log
    rng = np.random.default_rng(seed)
    frames = list(exp.frames)
    t = last.time_s + 1.0 / fps
    while t <= log.time_s[-1] + 1e-9 and np.interp(t, log.time_s, log.displacement_mm) >= last.displacement_mm - 1e-6:
        name = f"images/hold_{len(frames):04d}.png"
        noisy = np.clip(np.round(image + rng.normal(0.0, 2.0, image.shape)), 0, 255).astype(np.uint8)
        save_png(folder / name, noisy)
        frames.append(replace(last, image=name, time_s=round(t, 4), force_N=None))
        t += 1.0 / fps
    write_toml_atomic(folder / TOML, experiment_to_toml(exp.with_frames(frames)))


def _elastoid(*args: str) -> float:
    """``elastoid ARGS`` in a child process; its peak resident memory in GB (from
    wait4: KB on Linux, bytes on macOS; the mesher's own child not counted)."""
    import os

    proc = subprocess.Popen([sys.executable, "-m", "app.cli", *args], cwd=ROOT, stdout=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise subprocess.CalledProcessError(proc.returncode, proc.args)
    return usage.ru_maxrss / (1e6 if sys.platform.startswith("linux") else 1e9)


def _errors(params: dict, truth: dict) -> str:
    return ", ".join(f"{params[f'E_{k}_kPa'] / v - 1:+.1%}" for k, v in truth.items() if f"E_{k}_kPa" in params)


def _confirmation(d: dict) -> str:
    """The findings on a thin margin diagnosed again on a finer mesh, in a few words ("" when none were)."""
    k = d.get("confirmation")
    if not k:
        return ""
    what = "+".join(k["effects"])
    if k["confirmed"] is None:
        return f"{what}: failed"
    there = k["candidates"].get(k["verdict"]) or k["candidates"][k["effects"][0]]
    how = "confirmed" if k["confirmed"] else "dropped"
    return (f"{what} {how} (ratio {k['ratio']:.2f}; finer: {k['excess_px']:.3f} / {k['floor_px']:.3f} px, "
            f"score {there['score']:+.0f}; {k['seconds']:.0f} s)")


def run(out: Path, name: str, seed_offset: int = 0, probe_edge_mm: float | None = None) -> list[str]:
    from app.core.effects import INFO
    from app.core.simulate import read_truth

    case = name
    seed, options, hidden = CASES[case]
    seed += seed_offset
    if seed_offset:
        name = f"{case}+{seed_offset}"
    folder = out / name
    if not (folder / "experiment.toml").is_file():
        _elastoid("simulate", str(folder), "--overwrite", "--seed", str(seed), *options)
        if case in HOLD_FPS:
            video_hold(folder, HOLD_FPS[case], seed)
    # the diagnosis of another identification mesh is written beside the automatic one's
    result = out / (f"{name}.json" if probe_edge_mm is None else f"{name}-probe-edge-{probe_edge_mm:g}.json")
    mesh = [] if probe_edge_mm is None else ["--probe-edge-mm", f"{probe_edge_mm:g}"]
    t = time.perf_counter()
    peak_gb = _elastoid("diagnose", str(folder), "--json", str(result), "--quiet", *mesh)
    seconds = time.perf_counter() - t
    d = json.loads(result.read_text())
    truth = read_truth(folder)
    hidden_regions = {r["name"] for r in truth.get("hidden_regions", [])}
    moduli = {k: v for k, v in truth["moduli_kPa"].items() if k not in hidden_regions}  # the described ones
    base = d["baseline"]
    verdict = d["verdict"] + (f" (near tie: {d['rival']})" if d.get("rival") else "")
    row = [name, hidden, verdict, "", "", "", _errors(base["parameters"], moduli), _confirmation(d),
           f"{seconds:.0f}", f"{peak_gb:.1f}"]
    ids = [c["effect"] for c in d["candidates"]]
    if hidden in ids:
        c = d["candidates"][ids.index(hidden)]
        key, unit = ("force_excess_N", "N") if INFO[hidden].channel == "force" else ("displacement_excess_px", "px")
        before = (c.get("reference_misfit") or base["misfit"])[key]
        after = c["misfit"].get(key)  # none when the candidate could not be fitted
        row[3] = f"{ids.index(hidden) + 1} ({c['score']:+.1f})"
        row[4] = _errors(c["parameters"], moduli)
        row[5] = ("not fitted" if after is None else "to the noise" if after <= 0
                  else f"{before / after:.1f}x ({before:.3g} -> {after:.3g} {unit})")
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "out" / "paper_effects")
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--seed-offset", type=int, default=0,
                    help="add this to every case's seed (a blind re-run on fresh noise, speckle and truth "
                         "meshes; its folders are named CASE+OFFSET)")
    ap.add_argument("--probe-edge-mm", type=float,
                    help="diagnose on an identification mesh with this element size on the probe face (default: "
                         "automatic; the demo's is 2.0 mm); its JSON is CASE-probe-edge-X.json")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    head = ["case", "hidden", "verdict", "hidden's rank (score)", "moduli with it (B, A)", "error falls with it",
            "baseline moduli (B, A)", "finer mesh (thin margin)", "diagnosis s", "peak GB"]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for name in args.cases.split(","):
        print("| " + " | ".join(run(args.out, name, args.seed_offset, args.probe_edge_mm)) + " |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
