"""`rig --sim` and `acquire` end to end, in subprocesses; a recording killed mid-run stays readable."""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from app.core.errors import ElastoidError

from app.core.experiment import read_experiment
from app.devices.cli import add_acquire_parser, add_rig_parser, main
from app.devices.sim import NonlinearSpring, ViscoelasticSpring, specimen_force_model

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
CLI = [sys.executable, "-m", "app.devices.cli"]


def _start_rig(*extra):
    proc = subprocess.Popen(CLI + ["rig", "--sim", "--contact-mm", "0.5", *extra], cwd=ROOT, env=ENV,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ports = {}
    while len(ports) < 2:
        line = proc.stdout.readline()
        assert line, f"rig --sim printed no ports: {proc.stderr.read()}"
        name, _, url = line.strip().partition(": ")
        ports[name] = url
    return proc, ports


def _stop_rig(proc):
    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=10) == 0


def _acquire(ports, out, *extra):
    return CLI + ["acquire", "--stage", ports["stage"], "--force", ports["force"], "--out", str(out),
                  "--approach-speed-mm-s", "2", "--sim-images", *extra]


def test_rig_and_acquire_end_to_end(tmp_path):
    proc, ports = _start_rig()
    try:
        run = subprocess.run(_acquire(ports, tmp_path / "rec", "--depth-mm", "1", "--speed-mm-s", "2",
                                      "--hold-s", "0.2", "--frames-at", "0,0.5,1"),
                             cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=60)
        assert run.returncode == 0, run.stderr
        assert run.stdout.strip() == str(tmp_path / "rec")
        assert "ramp     t=" in run.stderr and "the protocol completed" in run.stderr
        exp = read_experiment(tmp_path / "rec")
        assert [round(f.displacement_mm, 1) for f in exp.frames] == [0.0, 0.5, 1.0]
        assert exp.force_log.force_N.max() == pytest.approx(1.0 + 0.05, abs=0.1)
        # a recording has no moduli (no truth.toml, no [reference]): the simulated rig says so
        with pytest.raises(ElastoidError, match="truth.toml nor \\[reference\\]"):
            specimen_force_model(tmp_path / "rec", ("viscoelastic",))
        # a second recording into the same folder is refused before anything moves
        again = subprocess.run(_acquire(ports, tmp_path / "rec"), cwd=ROOT, env=ENV, capture_output=True,
                               text=True, timeout=30)
        assert again.returncode == 1 and "not empty" in again.stderr
    finally:
        _stop_rig(proc)


def test_killed_recording_leaves_a_readable_folder(tmp_path):
    proc, ports = _start_rig()
    out = tmp_path / "killed"
    try:
        acq = subprocess.Popen(_acquire(ports, out, "--depth-mm", "4", "--speed-mm-s", "0.5", "--frames-at",
                                        "0,0.25,3"),
                               cwd=ROOT, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        t_end = time.monotonic() + 20
        while time.monotonic() < t_end:
            toml = out / "experiment.toml"
            csv = out / "force.csv"
            if toml.exists() and "frame_001" in toml.read_text() and csv.read_text().count("\n") > 40:
                break
            time.sleep(0.05)
        acq.kill()  # SIGKILL mid-ramp: no cleanup runs
        assert acq.wait(timeout=10) == -signal.SIGKILL
        exp = read_experiment(out)
        assert len(exp.frames) == 2 and len(exp.force_log) > 40
        assert exp.force_log.displacement_mm.max() < 4.0  # it really was cut short
    finally:
        _stop_rig(proc)


def test_parsers_plug_into_a_main_parser():
    parser = argparse.ArgumentParser(prog="elastoid")
    sub = parser.add_subparsers(dest="command")
    add_rig_parser(sub)
    add_acquire_parser(sub)
    a = parser.parse_args(["acquire", "--stage", "loop://", "--force", "x", "--out", "o", "--frames-at", "0,5,10",
                           "--force-limit-N", "8"])
    assert a.frames_at == (0.0, 5.0, 10.0) and a.force_limit_N == 8.0 and callable(a.func)
    r = parser.parse_args(["rig", "--sim", "--effects", "viscoelastic,hyperelastic",
                           "--fault", "grbl_alarm:stage@t=4#1"])
    assert r.effects == ("viscoelastic", "hyperelastic") and r.fault[0]["at_s"] == 4.0 and callable(r.func)
    with pytest.raises(SystemExit):
        parser.parse_args(["rig", "--fault", "explode:stage"])


def test_acquire_reports_a_port_that_is_not_there(tmp_path, capsys):
    code = main(["acquire", "--stage", "/dev/does-not-exist", "--force", "loop://", "--out", str(tmp_path / "o")])
    assert code == 1 and "cannot open port /dev/does-not-exist" in capsys.readouterr().err
    assert main(["acquire", "--stage", "x", "--force", "y", "--out", str(tmp_path / "o"), "--depth-mm", "30"]) == 1


@pytest.mark.parametrize("args, says", [
    (["--depth-mm", "-3"], "argument --depth-mm: must be positive, got -3"),
    (["--speed-mm-s", "0"], "argument --speed-mm-s: must be positive, got 0"),
    (["--hold-s", "-1"], "argument --hold-s: must not be negative, got -1"),
    (["--force-limit-N", "x"], "argument --force-limit-N: expected a number, got 'x'"),
    (["--rate-hz", "nan"], "argument --rate-hz: expected a finite number"),
    (["--frames-at", "0,a"], "argument --frames-at: expected numbers separated by commas"),
])
def test_acquire_names_the_option_a_bad_value_came_in(tmp_path, capsys, args, says):
    """Refused before any port is opened or folder made, naming the option (they
    were named as the protocol's fields: 'depth_mm must be positive')."""
    out = tmp_path / "o"
    with pytest.raises(SystemExit) as exc:
        main(["acquire", "--stage", "/dev/does-not-exist", "--force", "loop://", "--out", str(out), *args])
    assert exc.value.code == 2 and says in capsys.readouterr().err and not out.exists()


def test_acquire_refuses_frames_beyond_the_depth(tmp_path, capsys):
    out = tmp_path / "o"
    code = main(["acquire", "--stage", "/dev/does-not-exist", "--force", "loop://", "--out", str(out),
                 "--depth-mm", "5", "--frames-at", "0,2.5,6"])
    err = capsys.readouterr().err
    assert code == 1 and "frames at 6 mm of travel lie outside 0..5 mm" in err and not out.exists()
    assert "cannot open port" not in err  # refused before the ports


def test_specimen_hook_without_an_experiment():
    m = specimen_force_model(None, (), contact_mm=1.5)
    assert isinstance(m, NonlinearSpring) and m.contact_mm == 1.5


def _hold_the_gil(seconds: float) -> None:
    """Stall this process as a busy window would: no other thread runs for ``seconds``."""
    old = sys.getswitchinterval()
    sys.setswitchinterval(10.0)
    try:
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            pass
    finally:
        sys.setswitchinterval(old)


def test_a_stalled_process_does_not_pass_for_a_dead_sensor():
    """The data of a stall waits in the port: the watchdog must read it before it judges.

    CI once failed a GUI jog with "no samples for 0.23 s" on a busy machine: the check ran
    after the stall and before the next read. Three 0.4 s stalls (twice the 0.2 s timeout)
    during a jog against the rig served by another process, as hardware would be.
    """
    import threading

    from app.devices.acquisition import Rig
    from app.devices.grbl import GrblStage
    from app.devices.loadcell import AsciiLoadCell

    proc, ports = _start_rig()
    try:
        rig = Rig(GrblStage.open(ports["stage"]), AsciiLoadCell.open(ports["force"]))
        assert rig.sensor_timeout_s < 0.4
        out = {}

        def jog():
            try:
                out["status"] = rig.jog(3.0, 1.0)
            except Exception as exc:  # reported below, with its message
                out["error"] = exc

        worker = threading.Thread(target=jog)
        worker.start()
        for _ in range(3):
            time.sleep(0.3)
            _hold_the_gil(0.4)
        worker.join(timeout=20)
        rig.close()
        assert "error" not in out, out.get("error")
        assert out["status"].travel_mm == pytest.approx(3.0, abs=0.01)
    finally:
        _stop_rig(proc)
