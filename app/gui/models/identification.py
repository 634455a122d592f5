"""Running an identification for the GUI, free of Qt.

:class:`IdentificationJob` holds what one run needs (the experiment as edited,
the mesh if there is one, the settings), calls ``app.core.identify`` from
whatever thread runs :meth:`IdentificationJob.run`, and leaves a trail that a
GUI timer reads: every cost evaluation goes into a thread-safe queue, and the
best overlay so far into a slot. Nothing here draws or touches a widget.
"""

from __future__ import annotations

import collections
import inspect
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from app.core.experiment import Experiment
from app.core.mesh import MeshSettings, TetMesh

from .session import IdentificationOutcome, IdentificationSettings

OVERLAY_PERIOD_S = 0.7  # at most this often, the worker renders the best overlay so far


@dataclass
class JobResult:
    outcome: IdentificationOutcome
    overlay: tuple | None  # (warped source, target, roi) at the result
    deformed: tuple | None  # (mesh points moved (n, 3) mm, displacement mm) at the target frame
    force: tuple | None  # (time s, measured N, model N) over the force log
    mesh: TetMesh | None  # the mesh the problem used
    history: list = field(default_factory=list)


def _core():
    from app.core import identify as core_identify

    return core_identify


def _accepts(fn: Callable, name: str) -> bool:
    try:
        params = inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return False
    return name in params or any(p.kind is p.VAR_KEYWORD for p in params.values())


class IdentificationJob:
    """One identification: ``run(stage, cancel)`` blocks; ``drain()`` hands new evaluations to the GUI.

    ``stage(text)`` receives coarse progress ("building the model", ...).
    ``backend`` is a module with ``Problem`` and ``identify`` (``app.core.identify`` by default).
    """

    def __init__(self, experiment: Experiment, settings: IdentificationSettings, *, mesh: TetMesh | None = None,
                 mesh_settings: MeshSettings | None = None, roi_px=None, frames: tuple[int, ...] | None = None,
                 target_frame: int | None = None, backend=None):
        self.experiment = experiment
        self.settings = settings
        self.mesh = mesh
        self.mesh_settings = mesh_settings
        self.roi_px = roi_px
        self.frames = frames
        self._target = target_frame
        self.backend = backend
        self.reports: collections.deque = collections.deque()
        self.evaluations = 0
        self.parameter_names: tuple[str, ...] = tuple(p.name for p in settings.parameters)
        self._overlay = None
        self._overlay_seq = 0
        self._lock = threading.Lock()
        self._best = np.inf
        self._best_params: dict | None = None
        self._last_overlay_t = -np.inf
        self.problem = None

    @property
    def target_frame(self) -> int:
        if self._target is not None:
            return self._target
        return self.frames[-1] if self.frames else len(self.experiment.frames) - 1

    # ---- read by the GUI (any thread) -----------------------------------------
    def drain(self) -> list:
        out = []
        while True:
            try:
                out.append(self.reports.popleft())
            except IndexError:
                return out

    def latest_overlay(self, seen: int) -> tuple[int, Any]:
        """(sequence number, overlay) when newer than ``seen``, else (seen, None)."""
        with self._lock:
            if self._overlay_seq > seen:
                return self._overlay_seq, self._overlay
        return seen, None

    # ---- the run (worker thread) --------------------------------------------------
    def _problem_kwargs(self, Problem) -> dict:
        kw: dict[str, Any] = dict(mesh=self.mesh, mesh_settings=self.mesh_settings, cost=self.settings.cost,
                                  nu=self.settings.nu)
        if self.roi_px is not None:
            kw["roi_px"] = tuple(self.roi_px)
        if self.frames is not None and _accepts(Problem.from_experiment, "frames"):
            kw["frames"] = tuple(self.frames)
        return {k: v for k, v in kw.items() if _accepts(Problem.from_experiment, k)}

    def _identify_kwargs(self, identify) -> dict:
        s = self.settings
        kw: dict[str, Any] = {"starts_kPa": tuple(s.starts_kPa), "max_evaluations": int(s.max_evaluations)}
        fixed = {p.name: p.value for p in s.parameters if not p.free}
        bounds = {p.name: (p.lower, p.upper) for p in s.parameters}
        if fixed and _accepts(identify, "fixed"):
            kw["fixed"] = fixed
        if _accepts(identify, "bounds"):
            kw["bounds"] = bounds
        return {k: v for k, v in kw.items() if _accepts(identify, k)}

    def _on_report(self, report) -> None:
        self.evaluations += 1
        self.reports.append(report)
        total = float(report.cost.get("total", np.inf))
        if total < self._best:
            self._best, self._best_params = total, dict(report.parameters)
        now = time.monotonic()
        if self._best_params is not None and now - self._last_overlay_t >= OVERLAY_PERIOD_S:
            self._last_overlay_t = now
            try:
                ov = self.problem.warped_source(self._best_params, self.target_frame)
            except Exception:  # an overlay is a view; never let it end the run
                return
            with self._lock:
                self._overlay = ov
                self._overlay_seq += 1

    def run(self, stage: Callable[[str], None], cancel: threading.Event) -> JobResult:
        core = self.backend or _core()
        Problem, identify = core.Problem, core.identify
        stage("building the model (mesh, finite elements, reduced basis)")
        self.problem = problem = Problem.from_experiment(
            self.experiment, progress=stage, cancel=cancel, **self._problem_kwargs(Problem))
        self.parameter_names = tuple(problem.parameter_names)
        if cancel.is_set():
            from app.core.errors import Cancelled

            raise Cancelled("identification cancelled")
        stage(f"identifying {', '.join(self.parameter_names)} from {len(self.settings.starts_kPa)} start(s)")
        result = identify(problem, progress=self._on_report, cancel=cancel, **self._identify_kwargs(identify))
        stage("rendering the result")
        params = dict(result.parameters)
        overlay = deformed = force = None
        try:
            overlay = problem.warped_source(params, self.target_frame)
        except Exception:
            pass
        try:
            d = float(self.experiment.frames[self.target_frame].displacement_mm)
            deformed = (np.asarray(problem.deformed_points(params, d)), d)
        except Exception:
            pass
        try:
            log = self.experiment.force_log
            force = (np.asarray(log.time_s), np.asarray(log.force_N), np.asarray(problem.model_force_N(params)))
        except Exception:
            pass
        ident = getattr(result, "identifiability", None)
        outcome = IdentificationOutcome(
            parameters={k: float(v) for k, v in params.items()},
            cost={k: float(v) for k, v in dict(result.cost).items()},
            evaluations=int(getattr(result, "evaluations", self.evaluations)),
            seconds=float(getattr(result, "seconds", 0.0)),
            identifiability=tuple(ident.lines()) if ident is not None else (),
            # the standard errors from the data when the report has them (the stated
            # 0.25 px noise model understates the scatter of the estimates)
            standard_error_rel=dict(getattr(ident, "standard_error_rel_data", None)
                                    or getattr(ident, "standard_error_rel", {}) or {}),
            flags=dict(getattr(ident, "flags", {}) or {}),
            starts=tuple(_start_summary(s) for s in (getattr(result, "starts", None) or ())),
            settings=self.settings,
        )
        mesh = getattr(problem, "mesh", None) or self.mesh
        return JobResult(outcome, overlay, deformed, force, mesh, list(getattr(result, "history", ()) or ()))


def _start_summary(s) -> dict:
    """A per-start summary as a plain dict, whatever shape the core gives it."""
    if isinstance(s, dict):
        return {k: (dict(v) if isinstance(v, dict) else v) for k, v in s.items()}
    out = {}
    for k in ("start", "start_kPa", "parameters", "cost", "evaluations"):
        if hasattr(s, k):
            v = getattr(s, k)
            out[k] = dict(v) if isinstance(v, dict) else v
    return out or {"value": str(s)}
