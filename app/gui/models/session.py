"""The session: what the user is working on, free of Qt.

One :class:`SessionModel` per window. It holds the experiment as read (never
written back), the specimen as edited in memory, the ROI and frame choice,
the mesh settings and mesh, the identification settings and the last result.
Panels observe its signals and change it through its methods; it saves to
and loads from a JSON session file that points at the experiment folder.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from app.core.errors import ElastoidError
from app.core.experiment import Experiment, Specimen, read_experiment
from app.core.geometry import Region
from app.core.identify import later_frames
from app.core.mesh import MeshSettings, TetMesh

from .signal import Signal

SESSION_FORMAT = "elastoid-session/1"
COSTS = {"joint": "NMI + force (joint)", "nmi": "NMI only (images)"}


class SessionError(ElastoidError):
    """A session file that cannot be used; names the file and the field."""

    def __init__(self, file, field: str, message: str):
        self.file, self.field, self.message = str(file), field, message
        super().__init__(f"{file}: {field}: {message}" if field else f"{file}: {message}")


# ---------------------------------------------------------------------------
# identification settings and outcome (plain data)
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class ParameterSpec:
    """One model parameter: free or fixed at ``value``, searched within [lower, upper]."""

    name: str
    free: bool = True
    value: float = 20.0  # the value it is held at when fixed
    lower: float = 0.1  # search bounds (used when the core takes per-parameter bounds)
    upper: float = 1.0e4
    unit: str = "kPa"


@dataclass(frozen=True)
class IdentificationSettings:
    parameters: tuple[ParameterSpec, ...] = ()
    cost: str = "joint"  # "joint" (images and force) | "nmi" (images only: fixes the ratios of the moduli)
    starts_kPa: tuple[float, ...] = (10.0, 20.0, 30.0, 40.0, 50.0, 60.0)
    nu: float = 0.49
    max_evaluations: int = 200  # per start
    all_frames: bool = True  # the source against every deformed frame, or only against the target

    def with_parameter(self, spec: ParameterSpec) -> "IdentificationSettings":
        return replace(self, parameters=tuple(spec if p.name == spec.name else p for p in self.parameters))

    def spec(self, name: str) -> ParameterSpec | None:
        return next((p for p in self.parameters if p.name == name), None)

    def to_json(self) -> dict:
        return {"parameters": [asdict(p) for p in self.parameters], "cost": self.cost,
                "starts_kPa": list(self.starts_kPa), "nu": self.nu, "max_evaluations": self.max_evaluations,
                "all_frames": self.all_frames}

    @classmethod
    def from_json(cls, d: dict) -> "IdentificationSettings":
        return cls(parameters=tuple(ParameterSpec(**p) for p in d.get("parameters", [])),
                   cost=d.get("cost", "joint"), starts_kPa=tuple(float(s) for s in d.get("starts_kPa", (20.0,))),
                   nu=float(d.get("nu", 0.49)), max_evaluations=int(d.get("max_evaluations", 200)),
                   all_frames=bool(d.get("all_frames", True)))


@dataclass(frozen=True)
class IdentificationOutcome:
    """What a finished identification leaves in the session (and in the session file)."""

    parameters: dict
    cost: dict
    evaluations: int
    seconds: float
    identifiability: tuple[str, ...] = ()
    standard_error_rel: dict = field(default_factory=dict)
    flags: dict = field(default_factory=dict)
    starts: tuple[dict, ...] = ()
    settings: IdentificationSettings | None = None
    mesh_check: tuple[str, ...] = ()  # the result identified again on a finer mesh, in words (Check the mesh)

    def to_json(self) -> dict:
        d = {k: getattr(self, k) for k in ("parameters", "cost", "evaluations", "seconds", "standard_error_rel", "flags")}
        d["identifiability"] = list(self.identifiability)
        d["mesh_check"] = list(self.mesh_check)
        d["starts"] = [dict(s) for s in self.starts]
        d["settings"] = self.settings.to_json() if self.settings else None
        return _jsonable(d)

    @classmethod
    def from_json(cls, d: dict) -> "IdentificationOutcome":
        s = d.get("settings")
        return cls(parameters=dict(d["parameters"]), cost=dict(d.get("cost", {})),
                   evaluations=int(d.get("evaluations", 0)), seconds=float(d.get("seconds", 0.0)),
                   identifiability=tuple(d.get("identifiability", ())),
                   standard_error_rel=dict(d.get("standard_error_rel", {})), flags=dict(d.get("flags", {})),
                   starts=tuple(d.get("starts", ())),
                   settings=IdentificationSettings.from_json(s) if s else None,
                   mesh_check=tuple(d.get("mesh_check", ())))


def _jsonable(x: Any):
    """Plain JSON types from numpy scalars, tuples and nested containers."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return v if math.isfinite(v) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.bool_,)):
        return bool(x)
    if x is None or isinstance(x, (str, int, bool)):
        return x
    return str(x)


# ---------------------------------------------------------------------------
# regions <-> JSON (the experiment format's fields)
# ---------------------------------------------------------------------------

_REGION_KEYS = {
    "background": (),
    "sphere": ("center_mm", "radius_mm"),
    "box": ("center_mm", "size_mm"),
    "cylinder": ("center_mm", "radius_mm", "height_mm", "axis"),
    "ellipsoid": ("center_mm", "radii_mm"),
    "surface": ("file",),
}


def region_to_json(r: Region) -> dict:
    d: dict[str, Any] = {"name": r.name, "kind": r.kind}
    for k in _REGION_KEYS[r.kind]:
        v = getattr(r, k)
        if v is not None:
            d[k] = list(v) if isinstance(v, tuple) else v
    return d


def region_from_json(d: dict, experiment: Experiment | None) -> Region:
    kind = d["kind"]
    if kind == "surface":
        if experiment is not None:
            for r in experiment.specimen.regions:
                if r.name == d["name"] and r.kind == "surface":
                    return r
        raise ValueError(f"surface region {d['name']!r} is not in the experiment")
    kw = {}
    for k in _REGION_KEYS[kind]:
        if k in d:
            v = d[k]
            kw[k] = tuple(float(x) for x in v) if isinstance(v, list) else float(v)
    return Region(name=d["name"], kind=kind, **kw)


def region_summary(r: Region) -> str:
    """A short description in mm for lists."""
    def v(t):
        return "(" + ", ".join(f"{x:g}" for x in t) + ")"
    if r.kind == "background":
        return "fills the specimen"
    if r.kind == "sphere":
        return f"centre {v(r.center_mm)}, radius {r.radius_mm:g}"
    if r.kind == "box":
        return f"centre {v(r.center_mm)}, size {v(r.size_mm)}"
    if r.kind == "cylinder":
        return f"centre {v(r.center_mm)}, radius {r.radius_mm:g}, height {r.height_mm:g}"
    if r.kind == "ellipsoid":
        return f"centre {v(r.center_mm)}, radii {v(r.radii_mm)}"
    return f"surface {r.file}"


def parameter_name(region_name: str) -> str:
    return f"E_{region_name}_kPa"


# ---------------------------------------------------------------------------
# the session
# ---------------------------------------------------------------------------


class SessionModel:
    """State of one window's work. Every change goes through a method that emits a signal."""

    def __init__(self) -> None:
        self.experiment: Experiment | None = None
        self.specimen: Specimen | None = None
        self.roi_px: tuple[int, int, int, int] | None = None
        self.source_frame = 0
        self.target_frame = 0
        self.mesh_settings: MeshSettings | None = None  # None: automatic sizes from the specimen (the core's)
        self.mesh: TetMesh | None = None
        self.mesh_quality: tuple[str, ...] = ()
        self.identification = IdentificationSettings()
        self.outcome: IdentificationOutcome | None = None
        self.overlay: tuple | None = None  # (warped ROI, target ROI, roi, valid mask) from the model
        self.deformed: tuple[np.ndarray, float] | None = None  # mesh points moved (n, 3) mm, at displacement mm
        self.session_path: Path | None = None
        self.locked_by: str | None = None  # a running computation that depends on the inputs
        self._frames: dict[int, np.ndarray] = {}

        self.experiment_changed = Signal()  # () - everything below may have changed too
        self.specimen_changed = Signal()  # ()
        self.roi_changed = Signal()  # (roi)
        self.frames_changed = Signal()  # (source, target)
        self.mesh_settings_changed = Signal()  # (settings)
        self.mesh_changed = Signal()  # ()
        self.identification_changed = Signal()  # (settings)
        self.outcome_changed = Signal()  # ()
        self.overlay_changed = Signal()  # ()
        self.deformed_changed = Signal()  # ()
        self.lock_changed = Signal()  # (reason or None): inputs (ROI, frames, specimen) are read-only while set

    # ---- lock ------------------------------------------------------------------
    def set_locked(self, reason: str | None) -> None:
        """While a computation uses the inputs, panels keep them read-only (``reason`` says why)."""
        if reason != self.locked_by:
            self.locked_by = reason
            self.lock_changed.emit(reason)

    # ---- experiment -----------------------------------------------------------
    @property
    def has_experiment(self) -> bool:
        return self.experiment is not None

    def open_experiment(self, folder: str | Path) -> Experiment:
        """Read the experiment folder (raises ExperimentError) and reset the work on it."""
        exp = read_experiment(Path(folder))
        self._set_experiment(exp)
        return exp

    def _set_experiment(self, exp: Experiment) -> None:
        self.experiment = exp
        self.specimen = exp.specimen
        self._frames = {}
        self.source_frame = 0
        self.target_frame = len(exp.frames) - 1
        shape = self.frame(0).shape
        from app.core.images import default_roi

        self.roi_px = tuple(int(x) for x in default_roi(exp, shape))
        self.mesh = None
        self.mesh_quality = ()
        self.identification = self._default_identification(exp.specimen, self.identification)
        self.outcome = None
        self.overlay = None
        self.deformed = None
        self.model_force_N = None
        self.session_path = None
        self.experiment_changed.emit()

    def frame(self, i: int) -> np.ndarray:
        """Frame i as float grey levels (cached)."""
        if i not in self._frames:
            self._frames[i] = self.experiment.image(i)
        return self._frames[i]

    @property
    def image_shape(self) -> tuple[int, int] | None:
        return None if self.experiment is None else self.frame(0).shape

    def analysis_frames(self) -> tuple[int, ...]:
        """Frame indices for the identification: the source first, then the target(s)."""
        exp, src, tgt = self.experiment, self.source_frame, self.target_frame
        if not self.identification.all_frames:
            return (src, tgt)
        later = later_frames(exp, src, keep=(tgt,))  # at most MAX_DEFAULT_FRAMES in all
        return (src,) + (later if tgt in later else later + (tgt,))

    def reference_kPa(self) -> dict[str, float]:
        """Reference moduli by parameter name (empty when the experiment has none)."""
        if self.experiment is None:
            return {}
        return {parameter_name(k): v for k, v in self.experiment.reference_moduli_kPa(self.identification.nu).items()}

    def analysis_experiment(self) -> Experiment:
        """The experiment with the edited specimen and the chosen ROI, in memory only."""
        exp = self.experiment
        imaging = replace(exp.imaging, roi_px=tuple(self.roi_px) if self.roi_px else exp.imaging.roi_px)
        return replace(exp, specimen=self.specimen, imaging=imaging)

    # ---- images -----------------------------------------------------------------
    def clamp_roi(self, roi) -> tuple[int, int, int, int]:
        rows, cols = self.image_shape
        c0, r0, c1, r1 = (int(round(v)) for v in roi)
        c0 = min(max(c0, 0), cols - 2)
        r0 = min(max(r0, 0), rows - 2)
        c1 = min(max(c1, c0 + 2), cols)
        r1 = min(max(r1, r0 + 2), rows)
        return (c0, r0, c1, r1)

    def set_roi(self, roi) -> None:
        roi = self.clamp_roi(roi)
        if roi != self.roi_px:
            self.roi_px = roi
            self._invalidate_result()
            self.roi_changed.emit(roi)

    def set_frames(self, source: int, target: int) -> None:
        n = len(self.experiment.frames)
        source, target = int(min(max(source, 0), n - 1)), int(min(max(target, 0), n - 1))
        if (source, target) != (self.source_frame, self.target_frame):
            self.source_frame, self.target_frame = source, target
            self._invalidate_result()
            self.frames_changed.emit(source, target)

    # ---- specimen -----------------------------------------------------------------
    def set_region(self, region: Region) -> None:
        """Add or replace a region (by name) in the in-memory specimen."""
        self._set_specimen(self.specimen.with_region(region))

    def remove_region(self, name: str) -> None:
        regs = tuple(r for r in self.specimen.regions if r.name != name)
        if len(regs) == len(self.specimen.regions) or not regs or regs[0].kind != "background":
            return
        self._set_specimen(replace(self.specimen, regions=regs))

    def reset_specimen(self) -> None:
        self._set_specimen(self.experiment.specimen)

    @property
    def specimen_edited(self) -> bool:
        return self.experiment is not None and self.specimen != self.experiment.specimen

    def _set_specimen(self, specimen: Specimen) -> None:
        if specimen == self.specimen:
            return
        self.specimen = specimen
        self.identification = self._default_identification(specimen, self.identification)
        self.set_mesh(None)
        self._invalidate_result()
        self.specimen_changed.emit()
        self.identification_changed.emit(self.identification)

    def new_region_name(self) -> str:
        used = set(self.specimen.region_names)
        for c in "ABCDEFGHIJKLMNOPQRSTUVWXYZ":
            if c not in used:
                return c
        return f"R{len(used)}"

    # ---- mesh ---------------------------------------------------------------------
    def effective_mesh_settings(self) -> MeshSettings:
        """The sizes a mesh gets now: the chosen ones, or the core's automatic ones."""
        if self.mesh_settings is not None or self.specimen is None:
            return self.mesh_settings or MeshSettings()
        from app.core.mesh import auto_settings

        return auto_settings(self.specimen.size_mm, self.experiment.probe.face_rect_mm(), self.specimen.regions)

    def set_mesh_settings(self, settings: MeshSettings | None) -> None:
        if settings != self.mesh_settings:
            self.mesh_settings = settings
            self.mesh_settings_changed.emit(settings)

    def set_mesh(self, mesh: TetMesh | None, quality_lines=()) -> None:
        self.mesh = mesh
        self.mesh_quality = tuple(quality_lines)
        if self.deformed is not None:
            self.deformed = None
            self.deformed_changed.emit()
        self.mesh_changed.emit()

    # ---- identification -------------------------------------------------------------
    @staticmethod
    def _default_identification(specimen: Specimen, old: IdentificationSettings) -> IdentificationSettings:
        specs = []
        for r in specimen.regions:
            name = parameter_name(r.name)
            prev = old.spec(name)
            specs.append(prev if prev is not None else ParameterSpec(name=name))
        return replace(old, parameters=tuple(specs))

    def set_identification(self, settings: IdentificationSettings) -> None:
        if settings != self.identification:
            self.identification = settings
            self.identification_changed.emit(settings)

    def set_outcome(self, outcome: IdentificationOutcome | None, overlay=None, deformed=None) -> None:
        self.outcome = outcome
        self.outcome_changed.emit()
        self.set_overlay(overlay)
        self.deformed = deformed
        self.deformed_changed.emit()

    def set_mesh_check(self, lines) -> None:
        """The outcome's mesh check (kept in the session file and the report)."""
        if self.outcome is not None:
            self.outcome = replace(self.outcome, mesh_check=tuple(lines))
            self.outcome_changed.emit()

    def set_overlay(self, overlay) -> None:
        self.overlay = overlay
        self.overlay_changed.emit()

    def _invalidate_result(self) -> None:
        self.model_force_N = None
        if self.outcome is not None or self.overlay is not None or self.deformed is not None:
            self.outcome = None
            self.overlay = None
            self.deformed = None
            self.outcome_changed.emit()
            self.overlay_changed.emit()
            self.deformed_changed.emit()

    # ---- session files -----------------------------------------------------------------
    def to_json(self, session_path: Path | None = None, model_check: dict | None = None) -> dict:
        if self.experiment is None:
            raise SessionError(session_path or "session", "experiment", "no experiment is open")
        exp_path = Path(self.experiment.path).resolve()
        d: dict[str, Any] = {"format": SESSION_FORMAT, "experiment": str(exp_path)}
        if session_path is not None:
            try:
                d["experiment_relative"] = str(Path(_relpath(exp_path, Path(session_path).resolve().parent)))
            except ValueError:  # another drive
                pass
        d["roi_px"] = list(self.roi_px) if self.roi_px else None
        d["source_frame"], d["target_frame"] = self.source_frame, self.target_frame
        d["specimen_regions"] = [region_to_json(r) for r in self.specimen.regions] if self.specimen_edited else None
        d["mesh_settings"] = asdict(self.mesh_settings) if self.mesh_settings is not None else None  # None: automatic
        d["identification"] = self.identification.to_json()
        d["result"] = self.outcome.to_json() if self.outcome else None
        if model_check:  # the model check's versions (see ModelCheckModel.state)
            d["model_check"] = model_check
        return _jsonable(d)

    def save_session(self, path: str | Path, model_check: dict | None = None) -> Path:
        """Write the session JSON (the experiment folder is only referred to, never written),
        with the model check's versions when given."""
        path = Path(path)
        if self.experiment is not None and path.resolve().parent == Path(self.experiment.path).resolve():
            raise SessionError(path, "", "sessions are not saved inside the experiment folder; choose another place")
        text = json.dumps(self.to_json(path, model_check), indent=2)
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_text(text, encoding="utf-8")
        tmp.replace(path)
        self.session_path = path
        return path

    def load_session(self, path: str | Path) -> dict | None:
        """Open a session file; returns the model check it kept (to rebuild), or None."""
        path = Path(path)
        try:
            d = json.loads(path.read_text(encoding="utf-8"))
        except OSError as exc:
            raise SessionError(path, "", f"cannot be read: {exc.strerror or exc}") from None
        except json.JSONDecodeError as exc:
            raise SessionError(path, "", f"is not valid JSON: {exc}") from None
        if not isinstance(d, dict) or d.get("format") != SESSION_FORMAT:
            raise SessionError(path, "format", f"must be {SESSION_FORMAT!r}, got {d.get('format') if isinstance(d, dict) else d!r}")
        exp_path = Path(d.get("experiment", ""))
        if not (exp_path / "experiment.toml").is_file() and d.get("experiment_relative"):
            alt = (path.parent / d["experiment_relative"]).resolve()
            if (alt / "experiment.toml").is_file():
                exp_path = alt
        exp = read_experiment(exp_path)
        self._set_experiment(exp)
        try:
            if d.get("specimen_regions"):
                regs = tuple(region_from_json(r, exp) for r in d["specimen_regions"])
                self._set_specimen(replace(exp.specimen, regions=regs))
            if "mesh_settings" in d:
                ms = d["mesh_settings"]
                self.set_mesh_settings(MeshSettings(**ms) if ms else None)
            if d.get("roi_px"):
                self.set_roi(d["roi_px"])
            self.set_frames(int(d.get("source_frame", 0)), int(d.get("target_frame", len(exp.frames) - 1)))
            if d.get("identification"):
                ident = IdentificationSettings.from_json(d["identification"])
                self.set_identification(self._default_identification(self.specimen, ident))
            if d.get("result"):
                self.set_outcome(IdentificationOutcome.from_json(d["result"]))
            checked = d.get("model_check")
            if checked is not None and not (isinstance(checked, dict) and isinstance(checked.get("history"), dict)):
                raise SessionError(path, "model_check", "must hold the model check's history")
        except (KeyError, TypeError, ValueError) as exc:
            raise SessionError(path, "", f"has a field ElastoID cannot use: {exc}") from None
        self.session_path = path
        return checked


def _relpath(target: Path, start: Path) -> str:
    import os

    return os.path.relpath(target, start)
