"""A whole simulated rig: GRBL stage + ELC-1 load cell + specimen, in virtual or real time."""

from __future__ import annotations

from app.devices.clock import VirtualClock
from app.devices.grbl import GrblStage
from app.devices.loadcell import AsciiLoadCell
from app.devices.sim.grbl import SimGrbl
from app.devices.sim.loadcell import SimLoadCell
from app.devices.sim.models import ForceModel, NonlinearSpring
from app.devices.sim.serve import SimServer
from app.devices.sim.world import FaultInjector, SimWorld, VirtualPort


class SimRig:
    """The simulated twins of the rig, coupled by ``model``.

    ``connect_virtual()`` returns connected drivers that run in virtual time
    (fast, deterministic: tests and the bench); ``serve()`` exposes the devices
    over pseudo-terminals (or TCP) in real time, for the GUI or ``elastoid rig --sim``.
    Faults are scheduled on ``rig.faults``.
    """

    def __init__(self, model: ForceModel | None = None, *, accel_mm_s2: float = 50.0,
                 max_speed_mm_s: float = 20.0, max_travel_mm: float = 50.0, noise_N: float = 0.002,
                 latency_ms: float = 5.0, full_scale_N: float = 50.0, axis: str = "Z", into_specimen: int = -1,
                 report_wpos: bool = False, seed: int = 0):
        self.model = model if model is not None else NonlinearSpring()
        self.axis = axis
        self.into_specimen = into_specimen
        start = 0.0 if into_specimen == -1 else -max_travel_mm
        self.grbl = SimGrbl(axis=axis, accel_mm_s2=accel_mm_s2, max_rate_mm_min=max_speed_mm_s * 60.0,
                            max_travel_mm=max_travel_mm, start_mpos=start, report_wpos=report_wpos,
                            wco=(1.0, 2.0, 3.0) if report_wpos else (0.0, 0.0, 0.0), seed=seed + 1)
        self.sensor = SimLoadCell(full_scale_N=full_scale_N, noise_N=noise_N, latency_ms=latency_ms, seed=seed + 2)
        self.faults = FaultInjector()
        self.world = SimWorld(self.model, self.grbl, self.sensor, into_specimen=into_specimen, faults=self.faults)
        self.clock: VirtualClock | None = None
        self.server: SimServer | None = None

    def connect_virtual(self, *, pace: float | None = None, connect: bool = True):
        """(stage driver, sensor driver, clock), talking to the twins in virtual time."""
        clock = VirtualClock(self.world.t, pace=pace)
        clock.on_advance = self.world.run_until
        self.clock = clock
        stage = GrblStage(VirtualPort(self.world, self.grbl, clock, "sim://stage"), axis=self.axis,
                          into_specimen=self.into_specimen, clock=clock)
        sensor = AsciiLoadCell(VirtualPort(self.world, self.sensor, clock, "sim://force"), clock=clock)
        if connect:
            stage.connect()
            sensor.identify()
        return stage, sensor, clock

    def serve(self, transport: str = "auto") -> SimServer:
        """Start serving in real time; ``.urls`` has the ports to open."""
        self.server = SimServer(self.world, transport=transport).start()
        return self.server

    def stop(self) -> None:
        if self.server is not None:
            self.server.stop()

    @property
    def contact_mm(self) -> float | None:
        """Travel at first contact, when the model says (both built-in models do)."""
        return getattr(self.model, "contact_mm", None)

    def true_travel_mm(self) -> float:
        return self.world.travel_mm()
