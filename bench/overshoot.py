"""Force overshoot of the safety stop on the simulated rig, over randomized runs.

Each run presses a nonlinear spring specimen (random stiffness, random contact
gap) at a random speed with a random sensor latency until the force limit
stops it; the peak of the *true* force (the model's, not the noisy reading) is
reported as a percentage of the limit. Runs in virtual time.

    /work/venv/bin/python bench/overshoot.py [--runs 100] [--seed 1] [--limit-N 10]

Target: the worst case never beyond 110 % of the limit.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.devices.acquisition import RampHoldUnload, Rig, SafetyLimits, default_template  # noqa: E402
from app.devices.sim import NonlinearSpring, SimRig  # noqa: E402


def one_run(rng: np.random.Generator, limit_N: float, folder: Path, accel: float) -> dict:
    speed = float(rng.uniform(0.2, 2.0))
    k = float(rng.uniform(0.5, 8.0))
    k3 = float(k * rng.uniform(0.0, 0.2))
    latency_ms = float(rng.uniform(0.0, 30.0))
    contact = float(rng.uniform(1.0, 3.0))
    sim = SimRig(NonlinearSpring(k, k3, contact), latency_ms=latency_ms, noise_N=0.002, accel_mm_s2=accel,
                 seed=int(rng.integers(1 << 30)))
    stage, sensor, clock = sim.connect_virtual()
    rig = Rig(stage, sensor, clock=clock, limits=SafetyLimits(force_limit_N=limit_N))
    rig.find_contact(speed_mm_s=1.0)
    res = rig.run(RampHoldUnload(19.0, speed, frames_at_mm=()), folder, default_template())
    true_peak = float(sim.world.truth()[2].max())
    return dict(speed=speed, k=k, k3=k3, latency_ms=latency_ms, outcome=res.outcome,
                true_pct=100 * true_peak / limit_N, meas_pct=100 * res.max_force_N / limit_N,
                stopped=res.stage_stopped)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=100)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--limit-N", type=float, default=10.0)
    ap.add_argument("--accel-mm-s2", type=float, default=50.0, help="stage acceleration (GRBL $122)")
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    rows = []
    t0 = time.perf_counter()
    print(f"{'run':>4} {'speed mm/s':>10} {'k N/mm':>7} {'k3 N/mm3':>8} {'latency ms':>10} {'outcome':>8} "
          f"{'true peak %':>11} {'read peak %':>11}")
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.runs):
            r = one_run(rng, args.limit_N, Path(tmp) / f"run{i:03d}", args.accel_mm_s2)
            rows.append(r)
            print(f"{i:4d} {r['speed']:10.2f} {r['k']:7.2f} {r['k3']:8.3f} {r['latency_ms']:10.1f} "
                  f"{r['outcome']:>8} {r['true_pct']:11.1f} {r['meas_pct']:11.1f}", flush=True)
    true = np.array([r["true_pct"] for r in rows])
    worst = int(np.argmax(true))
    all_safety = all(r["outcome"] == "safety" and r["stopped"] for r in rows)
    print()
    print(f"runs: {len(rows)} in {time.perf_counter() - t0:.1f} s (virtual time); all stopped by the force "
          f"limit and retracted: {'yes' if all_safety else 'NO'}")
    print(f"true peak force, % of the {args.limit_N:g} N limit: median {np.median(true):.1f}, "
          f"95th percentile {np.percentile(true, 95):.1f}, worst {true.max():.1f} (run {worst}: "
          f"{rows[worst]['speed']:.2f} mm/s, k {rows[worst]['k']:.2f} N/mm, latency "
          f"{rows[worst]['latency_ms']:.1f} ms)")
    ok = true.max() <= 110.0 and all_safety
    print(f"target (never beyond 110 %): {'met' if ok else 'NOT MET'}")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
