"""Model check at paper size: one hyperelastic forward solve and a full diagnosis
of the demo experiment (resources/demo: P2, 64,932 dofs on the mesh shipped since 2026-12-01).

    /work/venv/bin/python bench/diagnose.py [--repeats 3] [--skip-diagnose] [--skip-hyperelastic]
                                            [--candidates a,b,...]

Prints a table of medians over repeats. Targets: a hyperelastic forward solve
(all load steps to the demo's deepest travel, with the factorizations an
earlier solve left, as inside a fit) in at most 2 s; a full diagnosis in at
most 2 minutes. The first (cold) hyperelastic solve, which factorizes its
tangents, is reported separately. Each diagnosis runs as a user's first one:
with an empty mesh cache (the demo's mesh is the one shipped), so that the inclusion
candidate meshes its sphere every time. The diagnosis row also gives the CPU
time it used: a diagnosis keeps both cores busy, so its wall time follows its
CPU work (and this machine's speed of the day). It also gives the diagnosis'
peak resident memory (Linux: VmHWM, reset before each run).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def bench_hyperelastic(repeats: int) -> list[tuple[str, float, str]]:
    import numpy as np

    from app.core.experiment import read_experiment
    from app.core.forward import build_model
    from app.core.hyperelastic import HyperelasticModel
    from app.core.mesh import specimen_mesh

    exp = read_experiment(ROOT / "resources" / "demo")
    mesh = specimen_mesh(exp)
    fe = build_model(mesh)
    _, g = fe.solve([18.0, 63.0])
    depths = sorted({f.displacement_mm for f in exp.frames if f.displacement_mm > 0}
                    | {float(exp.force_log.displacement_mm.max())})
    steps = np.unique(np.concatenate([np.linspace(0, max(depths), 5)[1:], depths]))
    rows = []
    t = time.perf_counter()
    hm = HyperelasticModel(fe)
    rows.append(("hyperelastic setup (element data, sparsity)", time.perf_counter() - t, f"{fe.space.n_dofs} dofs"))
    t = time.perf_counter()
    sol = hm.solve([18.0, 63.0], 0.49, steps)
    cold = time.perf_counter() - t
    rows.append(("hyperelastic solve, cold (factorizes tangents)", cold,
                 f"{len(steps)} steps to {steps[-1]:.1f} mm, {hm.n_factorizations} factorizations, "
                 f"F/F_linear {sol.force_N[-1] / (g * steps[-1]):.3f}"))
    times, its = [], []
    rng = np.random.default_rng(0)
    for _ in range(repeats):
        E = [18.0 * rng.uniform(0.9, 1.1), 63.0 * rng.uniform(0.9, 1.1)]
        nf = hm.n_factorizations
        t = time.perf_counter()
        s = hm.solve(E, 0.49, steps)
        times.append(time.perf_counter() - t)
        its.append(f"{sum(s.iterations)} it/{hm.n_factorizations - nf} fact")
    rows.append(("hyperelastic solve, warm (median)", statistics.median(times),
                 f"moduli +-10%; {', '.join(its)}"))
    hm.free()
    return rows


def _cpu_seconds() -> float:
    """CPU time of this process and of its finished children (the mesher)."""
    import resource

    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def _reset_peak_rss() -> bool:
    """Start a new peak resident set (Linux: /proc/self/clear_refs); False when not possible."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _peak_rss_gb() -> float:
    """This process's peak resident set since the last reset (VmHWM), else since it started."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1e6
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6


def bench_diagnose(repeats: int, candidates) -> list[tuple[str, float, str]]:
    from app.core.diagnose import diagnose
    from app.core.experiment import read_experiment

    import gc
    import os
    import tempfile

    from app.core.mesh import shipped_mesh_path

    exp = read_experiment(ROOT / "resources" / "demo")
    if shipped_mesh_path(exp) is None:
        print("note: the demo's mesh is not shipped (resources/meshes): each run meshes it too")
    times, cpus, verdicts, per, peaks = [], [], [], {}, []
    saved = os.environ.get("ELASTOID_CACHE_DIR")
    for _ in range(repeats):
        # each run as a user's first: an empty cache, which takes the demo's mesh from the
        # copy shipped with ElastoID, so the inclusion candidate meshes its sphere every time
        with tempfile.TemporaryDirectory() as tmp:
            os.environ["ELASTOID_CACHE_DIR"] = tmp
            try:
                reset = _reset_peak_rss()
                t, c = time.perf_counter(), _cpu_seconds()
                d = diagnose(exp, candidates=candidates)
                times.append(time.perf_counter() - t)
                cpus.append(_cpu_seconds() - c)
                peaks.append((_peak_rss_gb(), reset))
            finally:
                if saved is None:
                    os.environ.pop("ELASTOID_CACHE_DIR", None)
                else:
                    os.environ["ELASTOID_CACHE_DIR"] = saved
        verdicts.append(d.verdict)
        for effect, seconds in [(cand.effect, cand.seconds) for cand in d.candidates]:
            per.setdefault(effect, []).append(seconds)
        del d  # its candidates' models would count in the next run's peak
        gc.collect()
    wall, cpu = statistics.median(times), statistics.median(cpus)
    rows = [("full diagnosis of the demo (median)", wall,
             f"verdict {', '.join(verdicts)}; {cpu:.0f} CPU-seconds (the mesher's included): "
             f"{cpu / wall:.2f} of the {os.cpu_count()} cores busy; peak memory "
             f"{max(p for p, _ in peaks):.1f} GB{'' if all(r for _, r in peaks) else ' (of the whole process)'}"
             " (the mesher's child process not counted)")]
    for e, ts in per.items():
        rows.append((f"  candidate {e}", statistics.median(ts),
                     "its scan, mesh and reduced model are built in the background while the others run"
                     if e == "inclusion" else ""))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--skip-diagnose", action="store_true")
    ap.add_argument("--skip-hyperelastic", action="store_true")
    ap.add_argument("--candidates", default="", help="effects to try in the diagnosis (default: all)")
    args = ap.parse_args(argv)
    rows = []
    if not args.skip_hyperelastic:
        rows += bench_hyperelastic(args.repeats)
    if not args.skip_diagnose:
        cands = [c for c in args.candidates.split(",") if c] or None
        rows += bench_diagnose(max(1, min(args.repeats, 2)), cands)
    width = max(len(r[0]) for r in rows)
    print(f"{'what':{width}s} {'seconds':>9s}  notes")
    for name, sec, note in rows:
        print(f"{name:{width}s} {sec:9.2f}  {note}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
