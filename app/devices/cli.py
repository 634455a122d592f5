"""Command-line plumbing for the instruments: ``elastoid rig`` and ``elastoid acquire``.

``add_rig_parser(subparsers)`` and ``add_acquire_parser(subparsers)`` register
the subcommands on an argparse parser; each sets ``func`` to a handler that
takes the namespace and returns the exit code. ``main(argv)`` is a stand-alone
entry (``python -m app.devices.cli rig --sim``).

Exit codes of ``acquire``: 0 the protocol completed, 3 a safety limit stopped
it, 4 a device fault ended it, 130 stopped with Ctrl-C, 1 it could not start.
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import threading
from pathlib import Path

EXIT_OK, EXIT_START, EXIT_SAFETY, EXIT_FAULT, EXIT_STOPPED = 0, 1, 3, 4, 130


def _csv_floats(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected numbers separated by commas, got {text!r}") from None


def _number(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return v


# argparse types (argparse names the option in its error); app.cli has its own, which
# the devices layer may not import
def _positive(text: str) -> float:
    v = _number(text)
    if not v > 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text}")
    return v


def _non_negative(text: str) -> float:
    v = _number(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"must not be negative, got {text}")
    return v


def _effects(text: str) -> tuple[str, ...]:
    return tuple(x.strip() for x in text.split(",") if x.strip())


def _fault(text: str):
    """KIND:DEVICE[@TRAVEL_MM | @t=SECONDS][#CODE], e.g. port_lost:stage@3.5 or grbl_alarm:stage@t=4#1."""
    from app.devices.sim import FAULT_KINDS

    head, _, where = text.partition("@")
    kind, _, device = head.partition(":")
    code = 1
    if "#" in where:
        where, _, c = where.partition("#")
        code = int(c)
    if kind not in FAULT_KINDS or device not in ("stage", "force"):
        raise argparse.ArgumentTypeError(
            f"fault must be KIND:DEVICE[@TRAVEL_MM|@t=S][#CODE] with KIND in {', '.join(FAULT_KINDS)} and "
            f"DEVICE stage or force, got {text!r}")
    at_s = at_travel = None
    if where.startswith("t="):
        at_s = float(where[2:])
    elif where:
        at_travel = float(where)
    return dict(kind=kind, device=device, at_s=at_s, at_travel_mm=at_travel, code=code)


# ---------------------------------------------------------------------------
# elastoid rig --sim
# ---------------------------------------------------------------------------


def add_rig_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "rig", help="serve a simulated rig (GRBL stage + force sensor) on serial ports",
        description="Start the simulated stage and force sensor, print their port addresses, run until Ctrl-C.")
    p.add_argument("--sim", action="store_true", help="simulate the rig (the only mode)")
    p.add_argument("--specimen", type=Path, help="experiment folder of the specimen to press against")
    p.add_argument("--effects", type=_effects, default=(), help="physical effects, comma-separated (e.g. viscoelastic)")
    p.add_argument("--contact-mm", type=float, default=2.0, help="gap the probe travels before touching (mm)")
    p.add_argument("--noise-N", type=float, default=0.002, help="sensor noise, standard deviation (N)")
    p.add_argument("--latency-ms", type=float, default=5.0, help="sensor latency (ms)")
    p.add_argument("--full-scale-N", type=float, default=50.0, help="sensor full scale (N)")
    p.add_argument("--accel-mm-s2", type=float, default=50.0, help="stage acceleration (mm/s^2)")
    p.add_argument("--max-travel-mm", type=float, default=50.0, help="stage travel (mm)")
    p.add_argument("--transport", choices=("auto", "pty", "socket"), default="auto",
                   help="pseudo-terminals, or TCP sockets where there are none")
    p.add_argument("--fault", type=_fault, action="append", default=[],
                   help="inject a fault: KIND:DEVICE[@TRAVEL_MM|@t=S][#CODE] (repeatable)")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=run_rig)
    return p


def run_rig(args) -> int:
    from app.devices.sim import SimRig, specimen_force_model

    if not args.sim:
        print("elastoid rig: only the simulated rig can be served; pass --sim", file=sys.stderr)
        return 2
    try:
        model = specimen_force_model(args.specimen, args.effects, contact_mm=args.contact_mm)
    except Exception as exc:  # a bad specimen folder: say why, no traceback
        print(f"elastoid rig: cannot build the specimen model: {exc}", file=sys.stderr)
        return EXIT_START
    sim = SimRig(model, noise_N=args.noise_N, latency_ms=args.latency_ms, full_scale_N=args.full_scale_N,
                 accel_mm_s2=args.accel_mm_s2, max_travel_mm=args.max_travel_mm, seed=args.seed)
    for f in args.fault:
        sim.faults.add(f["kind"], f["device"], at_s=f["at_s"], at_travel_mm=f["at_travel_mm"], code=f["code"])
    done = threading.Event()
    old = {s: signal.signal(s, lambda *_: done.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    server = sim.serve(args.transport)
    try:
        print(f"stage: {server.urls['stage']}")
        print(f"force: {server.urls['force']}")
        print("simulated rig running; Ctrl-C to stop", flush=True)
        while not done.wait(0.2):
            if server.error is not None:
                print(f"elastoid rig: the simulation stopped: {server.error}", file=sys.stderr)
                return EXIT_FAULT
        return EXIT_OK
    finally:
        sim.stop()
        for s, h in old.items():
            signal.signal(s, h)


# ---------------------------------------------------------------------------
# elastoid acquire
# ---------------------------------------------------------------------------


def add_acquire_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "acquire", help="record an indentation (ramp, hold, unload) into a new experiment folder",
        description="Find contact, run a ramp-hold-unload protocol and record it headless.")
    p.add_argument("--stage", required=True, help="stage port (device, socket://host:port, ...)")
    p.add_argument("--force", required=True, help="force sensor port")
    p.add_argument("--out", required=True, type=Path, help="new experiment folder to write")
    p.add_argument("--template", type=Path, help="experiment folder whose specimen/probe/imaging to copy")
    p.add_argument("--depth-mm", type=_positive, default=5.0, help="travel from contact to press to (mm, default 5)")
    p.add_argument("--speed-mm-s", type=_positive, default=0.5, help="loading speed (mm/s, default 0.5)")
    p.add_argument("--hold-s", type=_non_negative, default=10.0, help="hold at depth (s, default 10)")
    p.add_argument("--no-unload", action="store_true", help="stay at depth after the hold")
    p.add_argument("--frames-at", type=_csv_floats, default=(0.0,),
                   help="displacements from contact (mm, 0 to --depth-mm) to capture frames at (default 0)")
    p.add_argument("--force-limit-N", type=_positive, default=10.0,
                   help="force that stops the stage (N, default 10)")
    p.add_argument("--travel-limit-mm", type=_positive, default=20.0,
                   help="travel from contact that stops the stage (mm, default 20)")
    p.add_argument("--rate-hz", type=_positive, default=100.0, help="force sample rate (Hz, default 100)")
    p.add_argument("--approach-speed-mm-s", type=_positive, default=0.5,
                   help="speed while finding contact (mm/s, default 0.5)")
    p.add_argument("--contact-threshold-N", type=_positive, default=0.05,
                   help="force that marks contact (N, default 0.05)")
    p.add_argument("--max-approach-mm", type=_positive, default=20.0,
                   help="travel allowed to find contact (mm, default 20)")
    p.add_argument("--no-find-contact", action="store_true", help="the probe is at contact now: zero here")
    p.add_argument("--axis", default="Z", choices=("X", "Y", "Z"))
    p.add_argument("--into-specimen", type=int, default=-1, choices=(-1, 1),
                   help="sign of machine motion that presses into the specimen")
    p.add_argument("--baudrate", type=int, default=115200)
    p.add_argument("--unlock", action="store_true", help="unlock a stage found in alarm ($X)")
    img = p.add_mutually_exclusive_group()
    img.add_argument("--images", type=Path, help="folder the scanner exports frames into")
    img.add_argument("--sim-images", action="store_true", help="render simulated frames")
    p.set_defaults(func=run_acquire)
    return p


def _progress_line(stream):
    def show(p) -> None:
        d = "   --   " if p.displacement_mm is None else f"{p.displacement_mm:7.3f}"
        stream.write(f"\r{p.state:<8} t={p.time_s:7.2f} s  d={d} mm  F={p.force_N:8.3f} N  "
                     f"samples={p.samples:6d}  frames={p.frames:3d} ")
        stream.flush()
    return show


def run_acquire(args) -> int:
    from app.core.errors import ElastoidError
    from app.core.experiment import new_folder_problem, read_experiment
    from app.devices.acquisition import RampHoldUnload, Rig, SafetyLimits, default_template
    from app.devices.grbl import GrblStage
    from app.devices.imaging import FolderWatcher
    from app.devices.loadcell import AsciiLoadCell
    from app.devices.sim import SimulatedImageSource, speckle_render

    err = sys.stderr
    try:
        protocol = RampHoldUnload(depth_mm=args.depth_mm, speed_mm_s=args.speed_mm_s, hold_s=args.hold_s,
                                  unload=not args.no_unload, frames_at_mm=args.frames_at)
        limits = SafetyLimits(force_limit_N=args.force_limit_N, travel_limit_mm=args.travel_limit_mm)
        protocol.check(limits)
    except ValueError as exc:
        print(f"elastoid acquire: {exc}", file=err)
        return EXIT_START
    problem = new_folder_problem(args.out)
    if problem:
        print(f"elastoid acquire: {args.out} {problem}", file=err)
        return EXIT_START
    stage = sensor = None
    try:
        template = read_experiment(args.template, check_images=False) if args.template else default_template()
        stage = GrblStage.open(args.stage, baudrate=args.baudrate, axis=args.axis, into_specimen=args.into_specimen)
        if stage.last_status.alarm:
            if not args.unlock:
                print("elastoid acquire: the stage is in its alarm state; check the machine, then pass --unlock",
                      file=err)
                return EXIT_START
            stage.unlock()
        sensor = AsciiLoadCell.open(args.force, baudrate=args.baudrate)
    except ElastoidError as exc:
        print(f"elastoid acquire: {exc}", file=err)
        for dev in (stage, sensor):
            if dev is not None:
                dev.close()
        return EXIT_START
    rig = Rig(stage, sensor, limits=limits, sample_rate_hz=args.rate_hz)
    if args.images is not None:
        rig.images = FolderWatcher(args.images)
    elif args.sim_images and args.template:
        # the simulated scanner: B-mode frames of the template specimen's finite-element twin
        from app.devices.sim import specimen_twin

        twin = specimen_twin(args.template, progress=lambda s: print(f"elastoid acquire: {s}", file=err))
        rig.images = SimulatedImageSource(twin.frame, lambda: rig.displacement_mm() or 0.0)
    elif args.sim_images:
        roi = template.imaging.roi_px
        shape = (max(128, roi[3] if roi else 0), max(128, roi[2] if roi else 0))
        rig.images = SimulatedImageSource(speckle_render(shape, template.imaging.pixel_spacing_mm[1]),
                                          lambda: rig.displacement_mm() or 0.0)
    elif args.frames_at:
        print("elastoid acquire: no image source (--images or --sim-images): recording the force log only",
              file=err)
    stop = threading.Event()
    old = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    show = _progress_line(err)
    try:
        try:
            if args.no_find_contact:
                rig.zero_here()
            else:
                rig.find_contact(speed_mm_s=args.approach_speed_mm_s, threshold_N=args.contact_threshold_N,
                                 max_travel_mm=args.max_approach_mm, progress=show, stop=stop)
        except ElastoidError as exc:
            err.write("\n")
            note = getattr(exc, "stop_note", "")
            print(f"elastoid acquire: finding contact failed: {exc}" + (f" ({note})" if note else ""), file=err)
            return EXIT_STOPPED if stop.is_set() else EXIT_FAULT
        result = rig.run(protocol, args.out, template, progress=show, stop=stop)
        err.write("\n")
        print(f"elastoid acquire: {result.message} {result.samples} samples, {result.frames} frames in "
              f"{result.folder}" + (f"; {result.bad_lines} corrupted lines dropped" if result.bad_lines else ""),
              file=err)
        print(result.folder)
        return {"completed": EXIT_OK, "safety": EXIT_SAFETY, "stopped": EXIT_STOPPED}.get(result.outcome, EXIT_FAULT)
    finally:
        rig.close()
        for s, h in old.items():
            signal.signal(s, h)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="elastoid", description="ElastoID instruments")
    sub = parser.add_subparsers(dest="command", required=True)
    add_rig_parser(sub)
    add_acquire_parser(sub)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    raise SystemExit(main())
