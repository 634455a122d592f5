"""Device errors a user can read: each says, in plain words, what the device meant.

Every class derives from :class:`DeviceError` (itself an
:class:`app.core.errors.ElastoidError`), so a caller can catch all instrument
trouble in one place and show ``str(exc)`` to the user.
"""

from __future__ import annotations

from app.core.errors import ElastoidError


class DeviceError(ElastoidError):
    """Base of every instrument error. ``device`` names the instrument ("stage", "force sensor")."""

    def __init__(self, message: str, *, device: str = ""):
        self.device = device
        self.message = message
        super().__init__(f"{device}: {message}" if device else message)


class PortLost(DeviceError):
    """The serial port (or socket) could not be opened, or disappeared while in use."""


class DeviceTimeout(DeviceError):
    """The device did not answer within the time it should have."""


class ProtocolError(DeviceError):
    """The device answered something the driver does not understand."""


class GrblError(DeviceError):
    """GRBL rejected a command line with ``error:N``."""

    def __init__(self, code: int, command: str = ""):
        from app.devices.grbl import grbl_error_text

        self.code = code
        self.command = command
        self.meaning = grbl_error_text(code)
        where = f" to {command!r}" if command else ""
        super().__init__(f"GRBL answered error:{code}{where}: {self.meaning}", device="stage")


class GrblAlarm(DeviceError):
    """GRBL entered its alarm state with ``ALARM:N``; motion stopped and G-code is locked until ``$X``."""

    def __init__(self, code: int):
        from app.devices.grbl import grbl_alarm_text

        self.code = code
        self.meaning = grbl_alarm_text(code)
        super().__init__(
            f"GRBL alarm {code}: {self.meaning} The controller stopped and locked itself; "
            f"check the machine, then unlock it ($X) before moving again.", device="stage")


class SensorSaturated(DeviceError):
    """The force sensor reached its full scale: the true force is unknown (at least the full scale)."""

    def __init__(self, full_scale_N: float, force_N: float):
        self.full_scale_N = full_scale_N
        self.force_N = force_N
        super().__init__(
            f"the reading reached the sensor's full scale ({full_scale_N:g} N); the true force is at least "
            f"that and unknown, so the run was stopped", device="force sensor")


class SensorFault(DeviceError):
    """The force sensor flagged its own measurement as invalid (bridge or converter fault)."""


class SafetyStop(DeviceError):
    """The acquisition loop stopped the stage because a safety limit was crossed."""


class ForceLimitExceeded(SafetyStop):
    """The measured force reached the force limit."""


class TravelLimitExceeded(SafetyStop):
    """The probe reached the travel limit."""


class RigBusy(DeviceError):
    """A rig operation was asked for while another one is running."""


class EmergencyStop(SafetyStop):
    """The user pressed the emergency stop."""
