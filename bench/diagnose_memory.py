"""Where a diagnosis holds its memory, step by step.

    python bench/diagnose_memory.py EXPERIMENT [--confirm-below X]

Runs ``diagnose()`` on EXPERIMENT (every candidate, automatic mesh) with a thread
reading this process' resident memory every 0.1 s, and prints one row per
progress message: the seconds, the peak since the previous message, the memory
held at the message, and the step that ended. Then the verdict, the report's
``confirmed:`` and ``memory:`` lines, and the whole run's peak. Set
``ELASTOID_MEMORY_GB`` to see the lean paths a smaller machine takes, and
``ELASTOID_CACHE_DIR`` to reuse meshes. ``--confirm-below`` raises the thin-margin
threshold (app.core.diagnose.CONFIRM_BELOW) to force the finer mesh's
confirmation on a finding above it. Linux only (VmRSS). The figures of
docs/model-check.md, "The confirmation's memory", came from this script.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("experiment", type=Path)
    ap.add_argument("--confirm-below", type=float, help="the thin-margin threshold (default: the code's)")
    args = ap.parse_args()

    import app.core.diagnose as dg
    from app.core import memory
    from app.core.experiment import read_experiment

    if args.confirm_below is not None:
        dg.CONFIRM_BELOW = args.confirm_below
    peak, whole, stop = [0], [0], threading.Event()

    def sample():
        while not stop.is_set():
            r = memory.resident_bytes() or 0
            peak[0], whole[0] = max(peak[0], r), max(whole[0], r)
            time.sleep(0.1)

    threading.Thread(target=sample, daemon=True).start()
    t0, last = time.perf_counter(), ["start"]
    print(f"{'s':>7}  {'peak GB':>7}  {'held GB':>7}  step that ended")

    def say(text):
        held = (memory.resident_bytes() or 0) / 1e9
        print(f"{time.perf_counter() - t0:7.1f}  {peak[0] / 1e9:7.2f}  {held:7.2f}  {last[0][:100]}", flush=True)
        peak[0], last[0] = 0, text

    d = dg.diagnose(read_experiment(args.experiment), progress=say)
    say("end")
    stop.set()
    print(f"verdict: {d.verdict}")
    for line in d.lines():
        if line.startswith(("confirmed:", "not confirmed:", "memory:")):
            print(line)
    print(f"peak of the run: {whole[0] / 1e9:.2f} GB in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
