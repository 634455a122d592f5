"""The rig as the GUI sees it, free of Qt: an adapter over :mod:`app.devices`.

:class:`RigController` owns the :class:`app.devices.acquisition.Rig` and runs
every blocking operation (connect, jog, find contact, the protocol) on one
worker thread that calls :meth:`RigController.serve`; between operations it
streams the force so the plots stay live. Each force sample goes into a ring
buffer as it is read; the GUI draws from that buffer on a timer and reads the
latest :class:`RigStatus`. Results and errors go to ``on_event(kind, payload)``,
called on the worker thread (the Qt layer turns it into a signal).

The emergency stop works from any thread at any time.
"""

from __future__ import annotations

import math
import queue
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from app.core.errors import Cancelled

from .ringbuffer import RingBuffer

# columns of the live buffer
T, TRAVEL, DISP, FORCE = range(4)


@dataclass(frozen=True)
class RigSettings:
    stage_port: str = ""
    force_port: str = ""
    baudrate: int = 115200
    axis: str = "Z"
    into_specimen: int = -1
    rate_hz: float = 100.0
    force_limit_N: float = 10.0
    travel_limit_mm: float = 20.0
    approach_speed_mm_s: float = 0.5
    contact_threshold_N: float = 0.05
    max_approach_mm: float = 20.0
    jog_speed_mm_s: float = 2.0
    image_folder: str = ""  # where the scanner exports frames (real rig); empty: force only


@dataclass(frozen=True)
class RigStatus:
    """A snapshot the worker replaces as things happen (reading it is always safe)."""

    connected: bool = False
    simulated: bool = False
    operation: str = "disconnected"  # disconnected, connecting, idle, jog, contact, zero, run, stopping, paused
    state: str = ""  # the acquisition loop's state (idle, contact, ramp, hold, unload, retract, ...)
    travel_mm: float = math.nan
    displacement_mm: float | None = None
    force_N: float = math.nan
    contact_mm: float | None = None
    samples: int = 0
    frames: int = 0
    ports: str = ""
    message: str = ""


@dataclass(frozen=True)
class Protocol:
    depth_mm: float = 5.0
    speed_mm_s: float = 0.5
    hold_s: float = 10.0
    unload: bool = True
    frames_at_mm: tuple[float, ...] = (0.0, 1.0, 2.0, 3.0, 4.0, 5.0)


class _TeeSensor:
    """The force sensor, passing every sample it reads to ``sink`` as well."""

    def __init__(self, sensor, sink: Callable[[list], None]):
        self._sensor = sensor
        self._sink = sink

    def __getattr__(self, name):
        return getattr(self._sensor, name)

    def read_samples(self, timeout_s: float = 0.0):
        out = self._sensor.read_samples(timeout_s)
        if out:
            try:
                self._sink(out)
            except Exception:  # a display must never break the safety loop
                pass
        return out


class RigController:
    """Rig operations queued to one worker thread, live data in :attr:`buffer`."""

    def __init__(self, on_event: Callable[[str, Any], None] | None = None, *, buffer_s: float = 120.0,
                 rate_hz: float = 100.0):
        self.on_event = on_event or (lambda kind, payload: None)
        self.buffer = RingBuffer(int(buffer_s * rate_hz), 4)
        self.status = RigStatus()
        self.settings = RigSettings()
        self.rig = None
        self.sim = None
        self.last_recording: Path | None = None
        self._t0 = time.monotonic()
        self._commands: queue.Queue = queue.Queue()
        self._idle_stop = threading.Event()
        self._op_stop = threading.Event()
        self._quit = threading.Event()
        self._monitor_paused = False
        self._serving = False

    # ------------------------------------------------------------------ GUI thread
    def _submit(self, name: str, fn: Callable, *args) -> None:
        if self._quit.is_set():
            return
        self._commands.put((name, fn, args))
        self._idle_stop.set()

    def connect_ports(self, settings: RigSettings) -> None:
        self.settings = settings
        self._submit("connect", self._do_connect, settings, None)

    def start_simulated(self, settings: RigSettings, specimen_path: str | Path | None = None) -> None:
        self.settings = settings
        self._submit("connect", self._do_start_sim, settings, specimen_path)

    def disconnect(self) -> None:
        self._submit("disconnect", self._do_disconnect)

    def jog(self, delta_mm: float, speed_mm_s: float) -> None:
        self._submit("jog", self._do_jog, float(delta_mm), float(speed_mm_s))

    def find_contact(self) -> None:
        self._submit("contact", self._do_contact)

    def zero_here(self) -> None:
        self._submit("zero", self._do_zero)

    def unlock(self) -> None:
        self._submit("unlock", self._do_unlock)

    def run_protocol(self, protocol: Protocol, folder: str | Path, template, name: str | None = None) -> None:
        self._submit("run", self._do_run, protocol, Path(folder), template, name)

    def set_limits(self, force_limit_N: float, travel_limit_mm: float) -> None:
        """New limits apply to the very next sample (the loop reads them each time)."""
        from app.devices.acquisition import SafetyLimits

        self.settings = replace(self.settings, force_limit_N=force_limit_N, travel_limit_mm=travel_limit_mm)
        rig = self.rig
        if rig is not None:
            rig.limits = replace(rig.limits, force_limit_N=force_limit_N, travel_limit_mm=travel_limit_mm) \
                if isinstance(rig.limits, SafetyLimits) else SafetyLimits(force_limit_N, travel_limit_mm)

    def stop(self) -> None:
        """Stop the running operation the normal way (the rig halts, then retracts when that is safe)."""
        self._drop_pending()
        self._op_stop.set()

    def emergency_stop(self) -> None:
        """Halt the stage now, from any thread; the running operation ends without retracting."""
        self._drop_pending()
        rig = self.rig
        self._set_status(message="EMERGENCY STOP pressed")
        if rig is None:
            return

        def halt():
            try:
                rig.emergency_stop()
            except Exception as exc:  # reported, never raised into the GUI
                self.on_event("failed", ("stop", exc))

        threading.Thread(target=halt, name="elastoid-estop", daemon=True).start()

    def shutdown(self) -> None:
        """Stop everything; the worker then releases the ports and returns from :meth:`serve`."""
        self._drop_pending()
        self._quit.set()
        self._op_stop.set()
        self._idle_stop.set()
        self._commands.put(None)

    def _drop_pending(self) -> None:
        while True:
            try:
                self._commands.get_nowait()
            except queue.Empty:
                return

    # ------------------------------------------------------------------ worker thread
    def serve(self) -> None:
        """The worker's loop: run queued operations; stream the force in between. Returns on shutdown."""
        self._serving = True
        try:
            while not self._quit.is_set():
                try:
                    cmd = self._commands.get_nowait()
                except queue.Empty:
                    if self.rig is not None and not self._monitor_paused:
                        self._idle_stop.clear()
                        if self._commands.empty() and not self._quit.is_set():
                            self._monitor()
                        continue
                    cmd = self._commands.get()
                if cmd is None:
                    break
                name, fn, args = cmd
                self._monitor_paused = False
                self._op_stop.clear()
                self._set_status(operation=name, message="")
                self.on_event("started", name)
                try:
                    result = fn(*args)
                except BaseException as exc:  # every failure is reported; the loop lives on
                    self._set_status(operation="idle" if self.rig else "disconnected",
                                     message=_describe(exc))
                    self.on_event("failed", (name, exc))
                else:
                    self._set_status(operation="idle" if self.rig else "disconnected")
                    self.on_event("finished", (name, result))
        finally:
            self._do_disconnect(quiet=True)
            self._serving = False

    def _monitor(self) -> None:
        from app.devices.errors import EmergencyStop

        self._set_status(operation="idle")
        try:
            self.rig.monitor(self._idle_stop, progress=self._progress)
        except (EmergencyStop, Cancelled) as exc:
            self._set_status(message=_describe(exc))
            self.on_event("failed", ("monitor", exc))
        except BaseException as exc:
            self._monitor_paused = True
            self._set_status(operation="paused", message=_describe(exc))
            self.on_event("failed", ("monitor", exc))

    def _sink(self, samples) -> None:
        rig = self.rig
        if rig is None:
            return
        sess = rig.session
        contact = rig.contact_mm
        rows = np.empty((len(samples), 4))
        for i, s in enumerate(samples):
            travel = sess.travel_at(s.host_time_s) if sess is not None else math.nan
            rows[i] = (s.host_time_s - self._t0, travel, travel - contact if contact is not None else math.nan,
                       s.force_N)
        self.buffer.extend(rows)

    def _progress(self, p) -> None:
        self._set_status(state=p.state, travel_mm=p.travel_mm, displacement_mm=p.displacement_mm,
                         force_N=p.force_N, samples=p.samples, frames=p.frames,
                         contact_mm=self.rig.contact_mm if self.rig else None)

    def _set_status(self, **kw) -> None:
        self.status = replace(self.status, **kw)

    # ---- operations (worker thread) ------------------------------------------------
    def _open(self, settings: RigSettings, stage_url: str, force_url: str, simulated: bool):
        from app.devices.acquisition import Rig, SafetyLimits
        from app.devices.grbl import GrblStage
        from app.devices.loadcell import AsciiLoadCell

        self._do_disconnect(quiet=True, keep_sim=simulated)
        stage = GrblStage.open(stage_url, baudrate=settings.baudrate, axis=settings.axis,
                               into_specimen=settings.into_specimen)
        try:
            sensor = AsciiLoadCell.open(force_url, baudrate=settings.baudrate)
        except BaseException:
            stage.close()
            raise
        limits = SafetyLimits(force_limit_N=settings.force_limit_N, travel_limit_mm=settings.travel_limit_mm)
        self.rig = Rig(stage, _TeeSensor(sensor, self._sink), limits=limits, sample_rate_hz=settings.rate_hz)
        self.buffer.clear()
        st = stage.last_status
        info = sensor.info
        ports = f"stage {stage_url}, force {force_url}"
        self._set_status(connected=True, simulated=simulated, ports=ports,
                         travel_mm=st.travel_mm if st else math.nan, contact_mm=None)
        text = (f"connected: GRBL {stage.version or '?'} on {stage_url}; "
                f"{info.vendor} {info.model} (full scale {info.full_scale_N:g} N) on {force_url}")
        if st is not None and st.alarm:
            text += "; the stage is in its alarm state: check the machine, then Unlock"
            self._monitor_paused = True
        return text

    def _do_connect(self, settings: RigSettings, _unused) -> str:
        if not settings.stage_port or not settings.force_port:
            raise ValueError("enter the stage port and the force sensor port (e.g. /dev/ttyUSB0, COM3)")
        text = self._open(settings, settings.stage_port, settings.force_port, simulated=False)
        if settings.image_folder:
            from app.devices.imaging import FolderWatcher

            self.rig.images = FolderWatcher(settings.image_folder)
            text += f"; frames from the newest image in {settings.image_folder}"
        else:
            text += "; no image folder: the protocol records the force only"
        return text

    def _do_start_sim(self, settings: RigSettings, specimen_path) -> str:
        """Serve the simulated stage and sensor on virtual ports and connect to them like hardware.

        With ``specimen_path`` the rig presses against the finite-element twin of that
        experiment's specimen (force and B-mode frames); else against a generic soft spring.
        """
        from app.core.errors import ElastoidError
        from app.devices.sim import SimRig, SimulatedImageSource, specimen_force_model, speckle_render

        self._do_disconnect(quiet=True)
        twin, note = None, "a generic soft specimen"
        if specimen_path is not None:
            from app.devices.sim import specimen_twin

            self.on_event("progress", "building the specimen's finite-element twin (the first time it is meshed)")
            try:
                twin = specimen_twin(specimen_path, progress=lambda t: self.on_event("progress", f"twin: {t}"))
                note = "the finite-element twin of the open specimen"
            except ElastoidError as exc:
                self.on_event("progress", f"no twin ({exc}); using a generic soft specimen")
        if self._quit.is_set():
            raise Cancelled("the window closed while the simulated rig was starting")
        model = specimen_force_model(specimen_path if twin is not None else None)
        self.sim = SimRig(model)
        server = self.sim.serve()
        text = self._open(settings, server.urls["stage"], server.urls["force"], simulated=True)
        rig = self.rig
        render = twin.frame if twin is not None else speckle_render((160, 200), 0.2)
        rig.images = SimulatedImageSource(render, lambda: rig.displacement_mm() or 0.0)
        self.settings = replace(settings, stage_port=server.urls["stage"], force_port=server.urls["force"])
        return f"simulated rig started, pressing on {note}; " + text

    def _do_disconnect(self, quiet: bool = False, keep_sim: bool = False) -> str:
        rig, self.rig = self.rig, None
        if rig is not None:
            try:
                rig.close()
            except Exception:
                pass
        if self.sim is not None and not keep_sim:
            try:
                self.sim.stop()
            except Exception:
                pass
            self.sim = None
        if not quiet or rig is not None:
            self._set_status(connected=False, simulated=False, operation="disconnected", ports="", contact_mm=None,
                             displacement_mm=None)
        return "disconnected"

    def _need_rig(self):
        if self.rig is None:
            raise RuntimeError("the rig is not connected: connect to its ports or start the simulated rig")
        return self.rig

    def _do_jog(self, delta_mm: float, speed_mm_s: float) -> str:
        st = self._need_rig().jog(delta_mm, speed_mm_s, progress=self._progress, stop=self._op_stop)
        return f"jogged {delta_mm:+g} mm; travel {st.travel_mm:.3f} mm" if st else f"jogged {delta_mm:+g} mm"

    def _do_contact(self) -> str:
        s = self.settings
        c = self._need_rig().find_contact(speed_mm_s=s.approach_speed_mm_s, threshold_N=s.contact_threshold_N,
                                          max_travel_mm=s.max_approach_mm, progress=self._progress,
                                          stop=self._op_stop)
        self._set_status(contact_mm=c, displacement_mm=0.0)
        return f"contact found at travel {c:.3f} mm; displacement is now measured from there"

    def _do_zero(self) -> str:
        c = self._need_rig().zero_here()
        self._set_status(contact_mm=c, displacement_mm=0.0)
        return f"zeroed: contact set at travel {c:.3f} mm"

    def _do_unlock(self) -> str:
        self._need_rig().stage.unlock()
        return "stage unlocked"

    def _do_run(self, protocol: Protocol, folder: Path, template, name) -> Any:
        from app.devices.acquisition import RampHoldUnload, default_template

        rig = self._need_rig()
        p = RampHoldUnload(depth_mm=protocol.depth_mm, speed_mm_s=protocol.speed_mm_s, hold_s=protocol.hold_s,
                           unload=protocol.unload, frames_at_mm=tuple(protocol.frames_at_mm))
        result = rig.run(p, folder, template if template is not None else default_template(), name=name,
                         progress=self._progress, stop=self._op_stop)
        self.last_recording = result.folder
        return result


def _describe(exc: BaseException) -> str:
    text = str(exc) or type(exc).__name__
    note = getattr(exc, "stop_note", "")
    return f"{text} ({note})" if note else text
