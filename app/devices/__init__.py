"""Instruments: drivers over pyserial, their simulated twins, and the acquisition loop. No Qt here.

The GUI and the command line use:

* :class:`~app.devices.grbl.GrblStage` and :class:`~app.devices.loadcell.AsciiLoadCell`
  (``.open(url)``), behind the :class:`Stage` / :class:`ForceSensor` interfaces;
* :class:`~app.devices.imaging.FolderWatcher` or a simulated image source;
* :class:`~app.devices.acquisition.Rig` with :class:`SafetyLimits` and :class:`RampHoldUnload`;
* :class:`~app.devices.sim.SimRig` for the simulated twins.
"""

from app.devices.acquisition import Progress, RampHoldUnload, Recorder, Rig, RunResult, SafetyLimits, default_template
from app.devices.errors import (
    DeviceError,
    DeviceTimeout,
    EmergencyStop,
    ForceLimitExceeded,
    GrblAlarm,
    GrblError,
    PortLost,
    ProtocolError,
    RigBusy,
    SafetyStop,
    SensorFault,
    SensorSaturated,
    TravelLimitExceeded,
)
from app.devices.grbl import GrblStage
from app.devices.imaging import FolderWatcher, ImageFrame, ImageSource
from app.devices.interfaces import ForceSample, ForceSensor, SensorInfo, Stage, StageStatus
from app.devices.loadcell import AsciiLoadCell

__all__ = [
    "AsciiLoadCell", "DeviceError", "DeviceTimeout", "EmergencyStop", "FolderWatcher", "ForceLimitExceeded",
    "ForceSample", "ForceSensor", "GrblAlarm", "GrblError", "GrblStage", "ImageFrame", "ImageSource", "PortLost",
    "Progress", "ProtocolError", "RampHoldUnload", "Recorder", "Rig", "RigBusy", "RunResult", "SafetyLimits",
    "SafetyStop", "SensorFault", "SensorInfo", "SensorSaturated", "Stage", "StageStatus", "TravelLimitExceeded",
    "default_template",
]
