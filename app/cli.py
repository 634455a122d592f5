"""The command line: ``elastoid`` (the window), ``identify``, ``simulate`` and
the rig commands. Stable surface described in docs/cli.md."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import threading
import time
from pathlib import Path

from app.core.errors import Cancelled, ElastoidError

BASELINE_EFFECTS: tuple[str, ...] = ()


def _floats(text: str, n: int | None = None, what: str = "value") -> list[float]:
    """Comma-separated numbers of the option ``what``; an input error (exit 2)
    naming the option otherwise (an argparse error here was not caught: a
    traceback for `--starts a` or `--size-mm a`)."""
    try:
        vals = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ElastoidError(f"{what}: expected comma-separated numbers, got {text!r}") from None
    if n is not None and len(vals) != n:
        raise ElastoidError(f"{what}: expected {n} numbers, got {text!r}")
    return vals


def _given_inclusion(args, exp, effects) -> dict | None:
    """The current model's inclusion at ``--inclusion-at cx,cy,cz,r`` (mm, the
    specimen's frame), instead of locating it from the misfit; None without the
    option. A diagnosis whose verdict is an inclusion prints the sphere the
    identification placed it at in this form, so that the next step keeps it."""
    if not args.inclusion_at:
        return None
    if "inclusion" not in effects:
        raise ElastoidError("--inclusion-at places the inclusion effect's sphere: give --effects inclusion")
    *centre, radius = _floats(args.inclusion_at, 4, what="--inclusion-at")
    size = exp.specimen.size_mm
    if not all(0.0 < c < s for c, s in zip(centre, size)):
        raise ElastoidError(f"--inclusion-at: the centre ({', '.join(f'{c:g}' for c in centre)}) mm is outside the "
                            f"specimen ({' x '.join(f'{s:g}' for s in size)} mm, from its corner at 0, 0, 0)")
    if radius <= 0.0:
        raise ElastoidError(f"--inclusion-at: the radius must be positive, got {radius:g} mm")
    from app.core.effects.inclusion import new_region_name

    return {"name": new_region_name([r.name for r in exp.specimen.regions]), "center_mm": centre,
            "radius_mm": radius}


def _float(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None


def _ints(text: str, expected: str) -> list[int]:
    try:
        return [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None


def _positive(text: str) -> float:
    """argparse type: a positive number."""
    v = _float(text)
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"must be positive, got {text}")
    return v


def _poisson(text: str) -> float:
    """argparse type: a Poisson's ratio (-1 < nu < 0.5)."""
    from app.core.fem import poisson_problem

    v = _float(text)
    why = poisson_problem(v)
    if why:
        raise argparse.ArgumentTypeError(why)
    return v


def _indices(text: str) -> list[int]:
    """argparse type: comma-separated frame indices."""
    return _ints(text, "comma-separated frame indices like 0,2")


def _roi(text: str) -> list[int]:
    """argparse type: col0,row0,col1,row1, whole pixels."""
    expected = "four whole numbers col0,row0,col1,row1"
    vals = _ints(text, expected)
    if len(vals) != 4:
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
    return vals


# simulate: the option of each SyntheticSpec field its checks name
SPEC_OPTIONS = {"size_mm": "--size-mm", "nu": "--nu", "face_mm": "--face-mm", "depth_mm": "--depth-mm",
                "hold_s": "--hold-s", "force_noise_N": "--noise-N", "frames_at_mm": "--frames-at",
                "image_shape": "--rows/--cols", "regions": "--inclusion", "hidden_regions": "--hidden",
                "moduli_kPa": "--moduli", "g1": "--g1", "tau1_s": "--tau1-s", "truth_mesh_scale": "--truth-mesh-scale",
                "probe_center_mm": "--probe-center-mm", "lateral_axis": "--probe-turn-deg"}


def _moduli(text: str) -> dict:
    out = {}
    for part in text.split(","):
        k, _, v = part.partition("=")
        try:
            out[k.strip()] = float(v)
        except ValueError:
            raise ElastoidError(f"--moduli: expected NAME=kPa pairs like B=18,A=63, got {text!r}") from None
    return out


class TerminalProgress:
    """One status line on stderr, redrawn at most 10 times a second."""

    def __init__(self, enabled: bool, n_starts: int):
        self.enabled = enabled and sys.stderr.isatty()
        self.n_starts, self._last = n_starts, 0.0
        self.best = None

    def message(self, text: str) -> None:
        if self.enabled:
            sys.stderr.write(f"\r\033[K{text}")
            sys.stderr.flush()

    def __call__(self, rep) -> None:
        if self.best is None or rep.cost["total"] < self.best:
            self.best = rep.cost["total"]
        now = time.monotonic()
        if now - self._last < 0.1:
            return
        self._last = now
        width = 20
        done = int(width * (rep.start + min(rep.evaluation / 120, 1.0)) / self.n_starts)
        params = " ".join(f"{k[2:-4]}={v:.1f}" for k, v in rep.parameters.items())
        self.message(f"[{'#' * done}{'.' * (width - done)}] start {rep.start + 1}/{self.n_starts} "
                     f"eval {rep.evaluation:3d}  {params} kPa  NMI {rep.cost['nmi']:.4f}  "
                     f"F_rms {rep.cost['force_rms_N']:.3f} N")

    def done(self) -> None:
        if self.enabled:
            sys.stderr.write("\r\033[K")
            sys.stderr.flush()


def _check_json_dest(dest: str | None) -> None:
    """Before any computation: a --json FILE that cannot be written is reported
    now, not after the minutes (or, in a batch, hours) of the run."""
    if not dest or dest == "-":
        return
    path = Path(dest)
    if path.is_dir():
        raise ElastoidError(f"--json: {dest} is a folder; give a file name, e.g. {path / 'result.json'}")
    folder = path.parent
    if not folder.is_dir():
        raise ElastoidError(f"--json: cannot write {dest}: the folder {folder} does not exist")
    if not os.access(folder, os.W_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise ElastoidError(f"--json: cannot write {dest}: permission denied")


def _write_json(dest: str, payload: dict) -> bool:
    """Write the result (to standard output for "-"). A file is written whole or
    not at all (a temporary file renamed into place), so a script never reads half
    a result. When it cannot be written after all (disk full, the folder gone),
    the result goes to standard output instead, with the reason on standard
    error, and False is returned: the run's result is not lost."""
    text = json.dumps(payload, indent=2) + "\n"
    if dest == "-":
        sys.stdout.write(text)
        return True
    path = Path(dest)
    part = path.with_name(path.name + ".part")
    try:
        part.write_text(text, encoding="utf-8")
        os.replace(part, path)
    except OSError as exc:
        try:
            part.unlink()
        except OSError:
            pass
        sys.stdout.write(text)
        sys.stdout.flush()
        print(f"elastoid: --json: could not write {dest} ({exc.strerror or exc}); the result is on standard output "
              "above", file=sys.stderr)
        return False
    return True


def _check_effects(effects: list[str]) -> None:
    from app.core.effects import EFFECT_IDS, available

    for e in effects:
        if e not in EFFECT_IDS:
            raise ElastoidError(f"--effects: unknown effect {e!r}; the ids are {', '.join(EFFECT_IDS)}")
        if e not in available():
            raise ElastoidError(f"--effects: the effect {e!r} is not implemented in this version "
                                f"(available: {', '.join(available()) or 'none beyond the baseline'})")


def cmd_identify(args) -> int:
    from app.core.experiment import read_experiment
    from app.core.identify import Problem, check_roi, check_starts, frame_indices, identify

    effects = [e for e in (args.effects or "").split(",") if e]
    _check_effects(effects)
    if args.refine_inclusion and "inclusion" not in effects:
        raise ElastoidError("--refine-inclusion refines the inclusion effect's sphere: give --effects inclusion")
    if args.refine_inclusion and (args.roi or args.frames):
        raise ElastoidError("--refine-inclusion works on the experiment's ROI and frames, as the Model check "
                            "does: leave out --roi and --frames")
    _check_json_dest(args.json)
    starts = _floats(args.starts, what="--starts")
    check_starts(starts, "--starts")
    exp = read_experiment(args.experiment)
    given = _given_inclusion(args, exp, effects)
    frames = frame_indices(exp, args.frames, "--frames") if args.frames else None
    _say_thinned(exp, frames, args.quiet)
    bar = TerminalProgress(not args.quiet, len(starts))
    settings = _mesh_settings(args, exp)
    roi = check_roi(exp, args.roi, "--roi") if args.roi else None
    inclusion = None
    if effects:
        from app.core.diagnose import current_model, locate_inclusion
        from app.core.effects.model import identify_with_effects

        options = dict(roi_px=roi, frames=frames, cost=args.cost, nu=args.nu, similarity=args.similarity)
        try:
            if "inclusion" in effects:  # located from the misfit of the model without it, as a diagnosis does
                t_locate = time.perf_counter()
                inclusion = given or locate_inclusion(exp, effects, mesh_settings=settings, progress=bar.message,
                                                      **options)
                locate_seconds = round(time.perf_counter() - t_locate, 2)  # one figure for the JSON and the summary
                if args.refine_inclusion:
                    from app.core.diagnose import refine_located_inclusion

                    t_refine = time.perf_counter()
                    refinement = refine_located_inclusion(exp, effects, inclusion, mesh_settings=settings,
                                                          nu=args.nu, progress=bar.message)
                    refinement["seconds"] = round(time.perf_counter() - t_refine, 2)
                    inclusion = refinement["inclusion"]
            problem = current_model(exp, effects, mesh_settings=settings, inclusion=inclusion, progress=bar.message,
                                    **options)
            result = identify_with_effects(problem, starts, progress=bar)
        finally:
            bar.done()
    else:
        problem = Problem.from_experiment(exp, mesh_settings=settings, roi_px=roi, frames=frames, cost=args.cost,
                                          nu=args.nu, similarity=args.similarity, progress=bar.message)
        try:
            result = identify(problem, starts, progress=bar)
        finally:
            bar.done()
    result.effects = tuple(effects)
    result.experiment = str(args.experiment)
    check = None
    if args.mesh_check:  # the same model on a finer mesh, from this optimum
        from app.core.mesh_check import mesh_check

        bar = TerminalProgress(not args.quiet, 1)
        try:
            check = mesh_check(exp, effects, result.parameters, problem.mesh.n_nodes, mesh_settings=settings,
                               inclusion=inclusion, progress=bar.message, roi_px=roi, frames=frames,
                               cost=args.cost, nu=args.nu, similarity=args.similarity)
        except ElastoidError as exc:  # the identification stands: written and printed without the check
            print(f"elastoid: --mesh-check failed: {exc}", file=sys.stderr)
        finally:
            bar.done()
    payload = result.to_json_dict()
    payload["frames"] = list(problem.frames)  # the source first
    if check is not None:
        payload["mesh_check"] = check.to_dict()
    if inclusion is not None:  # its place is a parameter too (as in a diagnosis' candidate)
        payload["parameters"] = {**payload["parameters"], "center_mm": inclusion["center_mm"],
                                 "radius_mm": inclusion["radius_mm"]}
        # the fit's ``seconds`` leave out the locating (a fit, the tracking, the scan and the mesh)
        payload["inclusion"] = {**inclusion, "locate_seconds": locate_seconds, "given": given is not None}
        if args.refine_inclusion:
            located = refinement["located"]
            payload["inclusion"]["refinement"] = {
                "refined": refinement["refined"], "located_center_mm": located["center_mm"],
                "located_radius_mm": located["radius_mm"], "chi2_located": refinement["chi2_located"],
                "chi2_refined": refinement["chi2_refined"], "note": refinement["note"],
                "seconds": refinement["seconds"]}
    ref = exp.reference_moduli_kPa(args.nu)
    written = _write_json(args.json, payload) if args.json else True
    if args.json != "-":
        print(f"{exp.name}: {result.evaluations} evaluations in {result.seconds:.1f} s, cost {args.cost}")
        if inclusion is not None:
            from app.core.effects.inclusion import also_fits_text, place_text

            located = refinement["located"] if args.refine_inclusion else inclusion
            how = ("given by --inclusion-at" if given else
                   f"located from the misfit in {locate_seconds:.1f} s before the fit")
            print(f"  inclusion {inclusion['name']} (not in the experiment, {how}): centre {place_text(located)}")
            if located.get("also_fits"):
                print(f"  the place is uncertain: {also_fits_text(located, exp.specimen.size_mm[2])}")
            elif located.get("rival_fitted"):
                print(f"  another place was tried: {also_fits_text(located, exp.specimen.size_mm[2])}")
            if args.refine_inclusion:
                print(f"  {'refined' if refinement['refined'] else 'not refined'} in {refinement['seconds']:.1f} s"
                      f"{': centre ' + place_text(inclusion) if refinement['refined'] else ''}; "
                      f"{refinement['note']}")
        for name, val in result.parameters.items():
            region = name[2:-4] if name.startswith("E_") else ""
            extra = f"   (reference {ref[region]:.1f} kPa)" if region in ref else ""
            print(f"  {name} = {val:8.2f}{extra}")
        for k, v in result.ratios().items():
            if k.startswith("E_") and k.split("/")[0].endswith("_kPa"):
                print(f"  ratio {k} = {v:.3f}")
        print(f"  NMI {result.cost['nmi']:.4f}, force RMS misfit {result.cost['force_rms_N']:.4f} N")
        if result.identifiability is not None:
            for line in result.identifiability.lines():
                print(f"  {line}")
        if check is not None:
            ident = result.identifiability
            for line in check.lines(None if ident is None else ident.standard_error_rel_data):
                print(f"  {line}")
    return 0 if written else 1


def _say_thinned(exp, frames, quiet: bool) -> None:
    """Say on stderr when the default frames leave some out (later_frames)."""
    from app.core.identify import frame_indices, thinned_note

    note = thinned_note(exp, frame_indices(exp)) if frames is None else ""
    if note and not quiet:
        print(f"elastoid: {note}", file=sys.stderr)


def _add_mesh_options(parser) -> None:
    """The element-size options that :func:`_mesh_settings` reads (identify, diagnose)."""
    parser.add_argument("--mesh-edge-mm", type=_positive, help="element size far from the probe (default: automatic)")
    parser.add_argument("--probe-edge-mm", type=_positive, help="element size on the probe face (default: automatic)")
    parser.add_argument("--outline-edge-mm", type=_positive,
                        help="element size along the probe face's outline, where the model's error is largest "
                             "(default: the face's size)")
    parser.add_argument("--region-scale", type=_positive,
                        help="element size in and around the regions (a located inclusion's too) as a factor of the "
                             "automatic one, a fifth of each region's thinnest extent (default 1). At a hidden stiff "
                             "sphere's true place 0.5 fitted its modulus within 2%% where 1 fitted it 17%% low; about "
                             "twice the unknowns, time and memory")


def _mesh_settings(args, exp):
    from dataclasses import replace

    from app.core.mesh import auto_settings

    given = {k: v for k, v in (("edge_mm", args.mesh_edge_mm), ("probe_edge_mm", args.probe_edge_mm),
                               ("outline_edge_mm", args.outline_edge_mm),
                               ("region_scale", args.region_scale)) if v}
    if not given:
        return None
    # the sizes not given stay automatic (all of them: listing them again once dropped the outline)
    return replace(auto_settings(exp.specimen.size_mm, exp.probe.face_rect_mm(), exp.specimen.regions), **given)


def cmd_diagnose(args) -> int:
    from app.core.diagnose import diagnose
    from app.core.effects import EFFECT_IDS
    from app.core.experiment import read_experiment

    effects = [e for e in (args.effects or "").split(",") if e]
    _check_effects(effects)
    candidates = None
    if args.candidates:
        candidates = [e for e in args.candidates.split(",") if e]
        for e in candidates:
            if e not in EFFECT_IDS:
                raise ElastoidError(f"--candidates: unknown effect {e!r}; the ids are {', '.join(EFFECT_IDS)}")
    # a candidate already in the model is not tried; with none left there is nothing to diagnose
    left = [e for e in (candidates if candidates is not None else EFFECT_IDS) if e not in effects]
    if not left:
        what = "every effect" if candidates is None else ", ".join(candidates)
        raise ElastoidError(f"--candidates: {what} already in the current model (--effects {','.join(effects)}): "
                            "nothing to try")
    dropped = [e for e in (candidates or ()) if e in effects]
    if dropped and not args.quiet:
        print(f"elastoid: --candidates: {', '.join(dropped)} already in the current model, not tried",
              file=sys.stderr)
    _check_json_dest(args.json)
    from app.core.memory import limit_bytes

    limit_bytes()  # a malformed ELASTOID_MEMORY_GB is refused now, not after the first candidates
    exp = read_experiment(args.experiment)
    _say_thinned(exp, None, args.quiet)
    bar = TerminalProgress(not args.quiet, 1)
    t0 = time.perf_counter()
    settings = _mesh_settings(args, exp)
    try:
        inclusion = _given_inclusion(args, exp, effects)
        if "inclusion" in effects and inclusion is None:  # the current model's inclusion, located as a diagnosis does
            from app.core.diagnose import locate_inclusion

            inclusion = locate_inclusion(exp, effects, mesh_settings=settings, progress=bar.message)
        result = diagnose(exp, effects=effects, candidates=candidates, mesh_settings=settings, inclusion=inclusion,
                          progress=bar.message, confirm=not args.no_confirm)
    finally:
        bar.done()
    check = _diagnosis_mesh_check(args, exp, result, settings, inclusion) if args.mesh_check else None
    payload = result.to_json_dict()
    payload["experiment"] = str(args.experiment)
    payload["seconds"] = round(time.perf_counter() - t0, 2)
    if check is not None:
        payload["mesh_check"] = check.to_dict()
    written = _write_json(args.json, payload) if args.json else True
    if args.json != "-":
        print(f"{exp.name}: diagnosis in {time.perf_counter() - t0:.1f} s")
        for line in result.lines():
            print(f"  {line}")
        if check is not None:
            for line in check.lines():
                print(f"  {line}")
        placed = result.candidate("inclusion").sphere if result.verdict == "inclusion" else None
        if placed:  # the next step keeps the sphere the verdict's moduli were identified with
            at = ",".join(f"{v:g}" for v in (*placed["center_mm"], round(placed["radius_mm"], 2)))
            added = ",".join([*effects, "inclusion"])
            print(f"  next: add it with --effects {added} --inclusion-at {at}, for identify or the next diagnose "
                  f"(without --inclusion-at the sphere is located from the misfit again, where the place can differ)")
    return 0 if written else 1


def _diagnosis_mesh_check(args, exp, result, settings, inclusion):
    """The model the diagnosis calls for (its ``identified``: the verdict added, an
    inclusion at the place the identification found) identified again on a finer
    mesh (app.core.mesh_check); None when the diagnosis identified no model."""
    from app.core.effects.inclusion import sphere_of
    from app.core.mesh_check import mesh_check

    ident = result.identified
    if not ident:
        if not args.quiet:
            print("elastoid: --mesh-check: the diagnosis identified no model to check", file=sys.stderr)
        return None
    c = result.baseline if result.verdict == "none" else result.candidate(result.verdict)
    sphere = sphere_of(ident.get("inclusion") or c.inclusion or inclusion)
    mesh = getattr(c.problem, "mesh", None)
    bar = TerminalProgress(not args.quiet, 1)
    try:
        return mesh_check(exp, ident["effects"], ident["parameters"], None if mesh is None else mesh.n_nodes,
                          mesh_settings=settings, inclusion=sphere, progress=bar.message)
    except ElastoidError as exc:  # the diagnosis stands: written and printed without the check
        print(f"elastoid: --mesh-check failed: {exc}", file=sys.stderr)
        return None
    finally:
        bar.done()


def cmd_simulate(args) -> int:
    from app.core.geometry import Region
    from app.core.mesh import MeshSettings
    from app.core.simulate import DEMO_SPEC, PROBE_TURNS, SpecError, SyntheticSpec, simulate_experiment

    say = (lambda s: print(s, file=sys.stderr)) if not args.quiet else None
    if args.demo:
        print(simulate_experiment(args.output, DEMO_SPEC, progress=say, overwrite=args.overwrite))
        return 0
    size = tuple(_floats(args.size_mm, 3, "--size-mm"))
    regions = [Region("B", "background")]
    moduli = _moduli(args.moduli)
    if args.inclusion.lower() != "none":
        kind, _, nums = args.inclusion.partition(":")
        vals = _floats(nums, what="--inclusion")
        if kind == "sphere" and len(vals) == 4:
            regions.append(Region("A", "sphere", center_mm=tuple(vals[:3]), radius_mm=vals[3]))
        elif kind == "box" and len(vals) == 6:
            regions.append(Region("A", "box", center_mm=tuple(vals[:3]), size_mm=tuple(vals[3:])))
        else:
            raise ElastoidError("--inclusion: expected sphere:cx,cy,cz,r or box:cx,cy,cz,sx,sy,sz or none")
    hidden = []
    if args.hidden:
        kind, _, nums = args.hidden.partition(":")
        vals = _floats(nums, what="--hidden")
        if kind != "sphere" or len(vals) != 5:
            raise ElastoidError("--hidden: expected sphere:cx,cy,cz,r,E_kPa")
        hidden.append(Region("H", "sphere", center_mm=tuple(vals[:3]), radius_mm=vals[3]))
    effects = tuple(e for e in args.effects.split(",") if e)
    if "inclusion" in effects and not hidden:
        raise ElastoidError("--effects inclusion: give the undescribed region with --hidden sphere:cx,cy,cz,r,E_kPa")
    if hidden and "inclusion" not in effects:
        effects = effects + ("inclusion",)
    names = [r.name for r in regions]
    moduli = {k: v for k, v in moduli.items() if k in names}
    if hidden:
        moduli["H"] = vals[4]
    missing = [n for n in names if n not in moduli]
    if missing:
        raise ElastoidError(f"--moduli: no modulus for region(s) {', '.join(missing)}")
    spec = SyntheticSpec(size_mm=size, regions=tuple(regions), moduli_kPa=moduli, depth_mm=args.depth_mm,
                         face_mm=tuple(_floats(args.face_mm, 2, "--face-mm")),
                         frames_at_mm=tuple(_floats(args.frames_at, what="--frames-at")),
                         force_noise_N=args.noise_N, seed=args.seed, hold_s=args.hold_s, unload=args.unload,
                         image_shape=(args.rows, args.cols),
                         truth_mesh_scale=args.truth_mesh_scale,
                         effects=effects, hidden_regions=tuple(hidden), g1=args.g1, tau1_s=args.tau1_s,
                         nu=args.nu, lateral_axis=PROBE_TURNS[args.probe_turn_deg],  # degrees: "-x" reads as an option
                         probe_center_mm=(tuple(_floats(args.probe_center_mm, 2, "--probe-center-mm"))
                                          if args.probe_center_mm else None))
    try:
        out = simulate_experiment(args.output, spec, progress=say, overwrite=args.overwrite)
    except SpecError as exc:  # named by the option that set the field
        raise ElastoidError(f"{SPEC_OPTIONS.get(exc.field, exc.field)}: {exc.reason}") from None
    print(out)
    return 0


def cmd_selftest(args) -> int:
    from app.selftest import run_cli

    return run_cli(args)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="elastoid", description="Identify soft-tissue stiffness from robotic "
                                "ultrasound indentation. Without a command, opens the desktop application.")
    from app import __version__

    p.add_argument("--version", action="version", version=f"elastoid {__version__}")
    sub = p.add_subparsers(dest="command")

    ip = sub.add_parser("identify", help="fit the model's free parameters to an experiment")
    ip.add_argument("experiment", type=Path, help="the experiment folder (docs/experiment-format.md)")
    ip.add_argument("--effects", default="", help="physical effects added to the baseline (ids, comma-separated)")
    ip.add_argument("--json", metavar="FILE", help="write the result as JSON ('-' = standard output)")
    ip.add_argument("--cost", choices=("joint", "nmi"), default="joint",
                    help="joint: -NMI plus the force misfit (default); nmi: the paper's image-only cost")
    ip.add_argument("--similarity", choices=("smooth", "hard"), default="smooth",
                    help="NMI estimator of the cost: smooth (partial-volume bins, continuous; default) or hard "
                         "(the paper's fixed bins, equal to skimage's)")
    ip.add_argument("--frames", type=_indices, help="frame indices, the first is the source (default: 0 and every "
                    "later frame with more probe travel, at most 31 in all, spread along the probe's travel)")
    ip.add_argument("--roi", type=_roi, help="col0,row0,col1,row1 in pixels, ends exclusive (default: the "
                    "experiment's)")
    ip.add_argument("--starts", default="10,20,30,40,50,60", help="start moduli in kPa (the paper's by default)")
    ip.add_argument("--nu", type=_poisson, default=0.49, help="Poisson's ratio (default 0.49)")
    _add_mesh_options(ip)
    ip.add_argument("--inclusion-at", metavar="CX,CY,CZ,R", default="",
                    help="with --effects inclusion: the sphere's centre and radius in mm, instead of locating it "
                         "(a diagnosis with an inclusion verdict prints where the identification placed it)")
    ip.add_argument("--refine-inclusion", action="store_true",
                    help="with --effects inclusion: after locating the sphere, search its place and size as the "
                         "Model check's 'Refine the inclusion's place' does, and fit with the refined sphere when "
                         "it fits the measurements better (two to three minutes at the paper's size)")
    ip.add_argument("--mesh-check", action="store_true",
                    help="identify the result again on a mesh 0.7 times the size, to show how much of each "
                         "parameter is the mesh's own error (minutes at paper size)")
    ip.add_argument("--quiet", action="store_true", help="no progress line")
    ip.set_defaults(func=cmd_identify)

    dp = sub.add_parser("diagnose", help="find which physical effect the model misses")
    dp.add_argument("experiment", type=Path, help="the experiment folder (docs/experiment-format.md)")
    dp.add_argument("--effects", default="", help="effects already in the current model (ids, comma-separated)")
    dp.add_argument("--candidates", default="", help="effects to try (default: every effect not in the model)")
    dp.add_argument("--inclusion-at", metavar="CX,CY,CZ,R", default="",
                    help="with --effects inclusion: the current model's sphere, centre and radius in mm, instead of "
                         "locating it (as a diagnosis with an inclusion verdict prints it)")
    dp.add_argument("--json", metavar="FILE", help="write the result as JSON ('-' = standard output)")
    _add_mesh_options(dp)
    dp.add_argument("--mesh-check", action="store_true",
                    help="identify the model the diagnosis calls for again on a mesh 0.7 times the size, to show "
                         "how much of each parameter is the mesh's own error (minutes at paper size)")
    dp.add_argument("--no-confirm", action="store_true",
                    help="do not diagnose a finding on a thin margin again on a mesh 0.7 times the size before it "
                         "is the verdict (saves about a minute at paper size; the first mesh's verdict stands)")
    dp.add_argument("--quiet", action="store_true", help="no progress line")
    dp.set_defaults(func=cmd_diagnose)

    sp = sub.add_parser("simulate", help="write a synthetic experiment folder (with truth.toml)")
    sp.add_argument("output", type=Path, help="the experiment folder to write (new or empty, else --overwrite)")
    sp.add_argument("--seed", type=int, default=0, help="random seed of the speckle, the noise and the truth mesh (default 0)")
    sp.add_argument("--size-mm", default="90,90,96", help="specimen box x,y,z in mm (default: the paper's 90,90,96)")
    sp.add_argument("--inclusion", default="sphere:45,45,66,15",
                    help="sphere:cx,cy,cz,r | box:cx,cy,cz,sx,sy,sz | none (region A)")
    sp.add_argument("--moduli", default="B=18,A=63", help="kPa per region, e.g. B=18,A=63")
    sp.add_argument("--face-mm", default="40,10", help="probe face, lateral,elevation in mm (default 40,10)")
    sp.add_argument("--probe-center-mm", help="x,y of the probe face's centre on the top, mm (default: the top's "
                    "centre)")
    sp.add_argument("--probe-turn-deg", choices=("0", "90", "180", "270"), default="0",  # simulate.PROBE_TURNS
                    help="the probe turned about the vertical, degrees from x to the image columns (default 0: "
                         "along x; 90: along y)")
    sp.add_argument("--depth-mm", type=float, default=14.8, help="probe travel at the end of the loading, mm (default 14.8)")
    sp.add_argument("--frames-at", default="0,7.4,14.8", help="probe travel of each frame, mm")
    sp.add_argument("--hold-s", type=float, default=0.0, help="hold at the full travel, s (default 0; the probe moves at 1 mm/s)")
    sp.add_argument("--unload", action="store_true", help="unload after the hold, back to zero travel")
    sp.add_argument("--noise-N", type=float, default=0.02, help="force noise (standard deviation), N (default 0.02)")
    sp.add_argument("--rows", type=int, default=256, help="image rows (depth), pixels (default 256)")
    sp.add_argument("--cols", type=int, default=200, help="image columns (lateral), pixels (default 200)")
    sp.add_argument("--truth-mesh-scale", type=float, default=0.7,
                    help="truth mesh size relative to the automatic identification mesh (< 1: finer)")
    sp.add_argument("--effects", default="", help="physical effects in the truth (ids, comma-separated)")
    sp.add_argument("--hidden", default="", metavar="sphere:cx,cy,cz,r,E_kPa",
                    help="an inclusion in the truth that experiment.toml does not describe (the inclusion effect)")
    sp.add_argument("--g1", type=float, default=0.3, help="viscoelastic truth: relaxing fraction")
    sp.add_argument("--tau1-s", type=float, default=2.0, help="viscoelastic truth: relaxation time, s")
    sp.add_argument("--nu", type=float, default=0.49, help="Poisson's ratio of the truth")
    sp.add_argument("--demo", action="store_true",
                    help="write the bundled demo experiment (its fixed settings; the options above are ignored)")
    sp.add_argument("--overwrite", action="store_true", help="write into OUTPUT even if it is not empty (files of the same names are replaced)")
    sp.add_argument("--quiet", action="store_true", help="no progress line")
    sp.set_defaults(func=cmd_simulate)

    tp = sub.add_parser("selftest", help="check this installation: one PASS/FAIL line per check",
                        description="Import everything, mesh and solve a small specimen, render off screen, "
                        "talk to the simulated rig, build the window offscreen. Exit code 0 when all pass.")
    tp.add_argument("--with-3d", action="store_true", help="also build the window with its 3-D view (needs a display)")
    tp.add_argument("--only", help="comma-separated checks: imports, solver, resources, mesh, forward, render, "
                    "rig, window, window-3d")
    tp.set_defaults(func=cmd_selftest)

    try:
        from app.devices.cli import add_acquire_parser, add_rig_parser
    except ImportError:
        pass
    else:
        add_rig_parser(sub)
        add_acquire_parser(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--selftest"]:  # the installer's spelling: elastoid --selftest [--with-3d]
        argv = ["selftest", *argv[1:]]
    args = parser.parse_args(argv)
    if args.command is None:
        from app.gui import main as gui_main

        return gui_main([])
    try:
        return int(args.func(args) or 0)
    except ElastoidError as exc:
        print(f"elastoid: {exc}", file=sys.stderr)
        return 2
    except (Cancelled, KeyboardInterrupt):
        print("elastoid: stopped", file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
