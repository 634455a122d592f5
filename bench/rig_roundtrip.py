"""Rig round trip: the simulated rig presses against the demo specimen's
finite-element twin, `elastoid acquire` records an experiment from it over
serial ports, and `elastoid identify` recovers the moduli.

    python bench/rig_roundtrip.py [--specimen resources/demo] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--specimen", default=str(ROOT / "resources" / "demo"))
    ap.add_argument("--out", default=None)
    ap.add_argument("--depth-mm", type=float, default=14.8)
    args = ap.parse_args(argv)
    out = Path(args.out or tempfile.mkdtemp(prefix="elastoid-rig-")) / "recording"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    py = [sys.executable, "-m", "app.cli"]
    t0 = time.perf_counter()
    rig = subprocess.Popen(py + ["rig", "--sim", "--specimen", args.specimen], cwd=ROOT, env=env,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        ports = {}
        while len(ports) < 2:
            line = rig.stdout.readline()
            if not line:
                raise SystemExit(f"the simulated rig did not start: {rig.stderr.read()}")
            if ":" in line and line.split(":")[0] in ("stage", "force"):
                k, v = line.split(":", 1)
                ports[k] = v.strip()
        d = args.depth_mm
        acq = subprocess.run(py + ["acquire", "--stage", ports["stage"], "--force", ports["force"], "--out", str(out),
                                   "--template", args.specimen, "--sim-images", "--depth-mm", f"{d}",
                                   "--speed-mm-s", "2", "--hold-s", "0.5", "--frames-at", f"0,{d / 2},{d}",
                                   "--force-limit-N", "20", "--approach-speed-mm-s", "2"],
                             cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
        if acq.returncode != 0:
            raise SystemExit(f"acquire failed ({acq.returncode}): {acq.stderr[-2000:]}")
    finally:
        rig.terminate()
        rig.wait(timeout=30)
    t_acq = time.perf_counter() - t0
    ident = subprocess.run(py + ["identify", str(out), "--json", "-", "--quiet"], cwd=ROOT, env=env,
                           capture_output=True, text=True, timeout=900)
    if ident.returncode != 0:
        raise SystemExit(f"identify failed: {ident.stderr[-2000:]}")
    result = json.loads(ident.stdout)
    truth = tomllib.loads((Path(args.specimen) / "truth.toml").read_text())["moduli_kPa"]
    print(f"recorded {out} in {t_acq:.0f} s; identified in {result['seconds']:.1f} s")
    print("| parameter | identified (kPa) | simulated specimen (kPa) | error |")
    print("|---|---|---|---|")
    for region, val in truth.items():
        got = result["parameters"][f"E_{region}_kPa"]
        print(f"| E_{region}_kPa | {got:.2f} | {val:.2f} | {100 * (got / val - 1):+.1f}% |")


if __name__ == "__main__":
    main()
