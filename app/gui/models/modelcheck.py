"""The model check of the session's experiment, free of Qt.

:class:`ModelCheckModel` owns one :class:`app.core.diagnose.ModelCheck` (made for
the experiment as edited: ROI, specimen, mesh sizes, Poisson's ratio) and builds
the work functions a worker thread runs: identify with a set of effects,
diagnose, add an effect, revert to a version. Each work function returns a
:class:`Snapshot` (the history, the comparison of the current version, the last
diagnosis) that the panel shows once it is back on the GUI thread; the panel
never reads the core object while a worker changes it.

The formatting helpers below turn the core's results into the text, arrays and
rows the panel draws (also Qt-free, so they are tested without a window).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, replace
from typing import Any, Callable

import numpy as np

from app.core.effects.inclusion import place_text, sphere_of
from app.core.errors import ElastoidError

Work = Callable[[Callable[[str], None], threading.Event], Any]


@dataclass(frozen=True)
class Snapshot:
    """What the panel shows after a step: read-only views of the check's state."""

    history: Any  # app.core.diagnose.ModelHistory
    comparison: Any = None  # app.core.compare.Comparison of the current version
    diagnosis: Any = None  # app.core.diagnose.Diagnosis (the last one)
    diagnosed_version: int | None = None  # the version the diagnosis was made for
    action: str = ""  # "identify" | "diagnose" | "add" | "refine" | "revert" | "mesh-check"
    message: str = ""  # one line for the status bar and the log
    # the current version identified again on a finer mesh (action "mesh-check"): its lines
    mesh_check: tuple = ()


@dataclass(frozen=True)
class Inputs:
    """What a model check depends on; a new one is needed when any of it changes."""

    experiment_id: int
    specimen: Any
    roi_px: tuple | None
    mesh_settings: Any
    nu: float


class ModelCheckModel:
    """One model check at a time. ``check`` is None until the first identify."""

    def __init__(self, factory: Callable[..., Any] | None = None):
        self._factory = factory  # for tests: builds the core ModelCheck
        self.check = None
        self.inputs: Inputs | None = None
        self.snapshot: Snapshot | None = None

    # ---- inputs -----------------------------------------------------------------------
    @staticmethod
    def inputs_of(session) -> Inputs | None:
        if not session.has_experiment:
            return None
        return Inputs(id(session.experiment), session.specimen, tuple(session.roi_px) if session.roi_px else None,
                      session.effective_mesh_settings(), float(session.identification.nu))

    def reset(self) -> None:
        self.check, self.inputs, self.snapshot = None, None, None

    def stale(self, session) -> bool:
        """True when the inputs changed since this check was made (its versions are for other inputs)."""
        return self.check is not None and self.inputs != self.inputs_of(session)

    @property
    def history(self):
        return self.snapshot.history if self.snapshot else None

    @property
    def n_versions(self) -> int:
        h = self.history
        return len(h) if h is not None else 0

    @property
    def current_effects(self) -> tuple:
        h = self.history
        v = h.current_version if h is not None else None
        return v.effects if v is not None else ()

    @property
    def current_inclusion(self):
        h = self.history
        v = h.current_version if h is not None else None
        return v.inclusion if v is not None else None

    def diagnosis_is_current(self) -> bool:
        """The last diagnosis was made for the version that is current now (so its candidates can be added)."""
        s = self.snapshot
        return (s is not None and s.diagnosis is not None and s.history is not None
                and s.diagnosed_version == s.history.current)

    # ---- work for a worker thread ------------------------------------------------------
    def _make(self, session):
        from app.core.diagnose import ModelCheck

        make = self._factory or ModelCheck
        return make(session.analysis_experiment(), mesh_settings=session.effective_mesh_settings(),
                    nu=float(session.identification.nu))

    def identify_work(self, session, effects=()) -> Work:
        """Identify a model with ``effects`` (a new version). A new check starts when the
        inputs changed (or there is none yet); the work runs on the worker thread."""
        effects = tuple(effects)
        inputs = self.inputs_of(session)
        if inputs is None:
            raise ElastoidError("open an experiment first")
        new = self.check is None or inputs != self.inputs
        check = self._make(session) if new else self.check
        # the current version's inclusion, else (None) the check locates one from the misfit
        inclusion = self.current_inclusion if ("inclusion" in effects and not new) else None
        prev = self.snapshot if not new else None

        def work(progress, cancel):
            label = ", ".join(effects) or "baseline"
            progress(f"identifying the model ({label})")
            v = check.identify(effects, inclusion=inclusion, progress=progress, cancel=cancel,
                               note=f"identified ({label})")
            progress("comparing the model with the measurements")
            cmp = check.compare()
            return (check, inputs, Snapshot(check.history, cmp, prev.diagnosis if prev else None,
                                            prev.diagnosed_version if prev else None, "identify",
                                            f"version {v.index} identified: {v.label}; {_errors_text(v.misfit)}"))

        return work

    def diagnose_work(self, candidates=None) -> Work:
        check, prev, inputs = self._need_check(), self.snapshot, self.inputs
        candidates = tuple(candidates) if candidates is not None else None
        if candidates is not None and not candidates:
            raise ElastoidError("choose at least one candidate effect to try")

        def work(progress, cancel):
            d = check.diagnose(candidates, progress=progress, cancel=cancel)
            h = check.history
            return (check, inputs, Snapshot(h, prev.comparison, d, h.current, "diagnose",
                                                 f"diagnosis: verdict {d.verdict}"))

        return work

    def add_work(self, effect: str | None = None) -> Work:
        check = self._need_check()
        if not self.diagnosis_is_current():
            raise ElastoidError("the last diagnosis was made for another version: diagnose the current one first")
        d, dv, inputs = self.snapshot.diagnosis, self.snapshot.diagnosed_version, self.inputs
        effect = effect or d.verdict
        if effect == "none":
            raise ElastoidError("the diagnosis found no effect that earns its parameters: nothing to add")

        def work(progress, cancel):
            progress(f"adding {effect}")
            v = check.add(effect, progress=progress, cancel=cancel)
            progress("comparing the model with the measurements")
            cmp = check.compare()
            message = f"added {effect}: version {v.index}, {_errors_text(v.misfit)}"
            if v.warning:
                message += f". Warning: {v.warning}"
            return (check, inputs, Snapshot(check.history, cmp, d, dv, "add", message))

        return work

    def refine_work(self) -> Work:
        """Move and resize the current version's inclusion where it fits best (a new version)."""
        check, prev, inputs = self._need_check(), self.snapshot, self.inputs
        if "inclusion" not in self.current_effects:
            raise ElastoidError("the current version has no inclusion to refine: add one first")

        def work(progress, cancel):
            from app.core.diagnose import RefinementRefused

            try:
                v = check.refine_inclusion(progress=progress, cancel=cancel)
            except RefinementRefused as exc:  # an answer, not a failure: the version stays as it is
                return (check, inputs, Snapshot(check.history, prev.comparison, prev.diagnosis,
                                                prev.diagnosed_version, "refine", f"not refined: {exc}"))
            progress("comparing the model with the measurements")
            cmp = check.compare()
            message = f"refined the inclusion's place: version {v.index}, {_errors_text(v.misfit)}"
            if v.warning:
                message += f". Warning: {v.warning}"
            return (check, inputs, Snapshot(check.history, cmp, prev.diagnosis, prev.diagnosed_version,
                                            "refine", message))

        return work

    def mesh_check_work(self) -> Work:
        """The current version (its effects, inclusion sphere and parameters) identified
        again on a mesh 0.7 times the size, with the check's ROI, frames, cost and
        Poisson's ratio (app.core.mesh_check). Its lines are kept with the version
        (ModelCheck.record_mesh_check); nothing else changes."""
        check, prev, inputs = self._need_check(), self.snapshot, self.inputs
        v = check.history.current_version
        problem = check.problem
        options = dict(roi_px=problem.roi, frames=problem.frames, cost=problem.cost_kind, nu=problem.nu)
        exp, effects, params, nodes, settings = check.exp, v.effects, dict(v.parameters), problem.mesh.n_nodes, \
            check.mesh_settings

        def work(progress, cancel):
            from app.core.mesh_check import mesh_check

            mc = mesh_check(exp, effects, params, nodes, mesh_settings=settings, inclusion=sphere_of(v.inclusion),
                            progress=progress, cancel=cancel, **options)
            head = f"version {v.index} ({v.label})"
            lines = (head, *mc.lines())
            check.record_mesh_check(v.index, lines)  # kept with the version: session file and report
            return (check, inputs, replace(prev, history=check.history, action="mesh-check",
                                           message=f"{head}: {lines[1]}", mesh_check=lines))

        return work

    def revert_work(self, index: int) -> Work:
        check, prev, inputs = self._need_check(), self.snapshot, self.inputs
        if not 0 <= index < self.n_versions:
            raise ElastoidError(f"there is no version {index}")

        def work(progress, cancel):
            v = check.revert(index, progress, cancel)
            progress(f"version {index} is current again; comparing it with the measurements")
            cmp = check.compare()
            return (check, inputs, Snapshot(check.history, cmp, prev.diagnosis, prev.diagnosed_version,
                                                 "revert", f"reverted to version {index}: {v.label}"))

        return work

    def state(self, session) -> dict | None:
        """The versions and the last diagnosis to keep in a session file
        (app.core.diagnose.check_state), or None: no version yet, or versions made
        for other inputs."""
        from app.core.diagnose import check_state

        if self.snapshot is None or self.history is None or not len(self.history) or self.stale(session):
            return None
        return check_state(self.history, self.snapshot.diagnosis, self.snapshot.diagnosed_version)

    def restore_work(self, session, state: dict) -> Work:
        """Rebuild a saved model check (:meth:`state`) for the session's inputs."""
        from app.core.diagnose import ModelCheck

        inputs = self.inputs_of(session)
        if inputs is None:
            raise ElastoidError("open an experiment first")
        exp, ms, nu = session.analysis_experiment(), session.effective_mesh_settings(), float(session.identification.nu)

        def work(progress, cancel):
            progress("rebuilding the saved model check")
            check = ModelCheck.restored(exp, state, mesh_settings=ms, nu=nu, progress=progress, cancel=cancel)
            progress("comparing the model with the measurements")
            cmp = check.compare()
            v, n = check.history.current_version, len(check.history)
            what = f"{n} saved version{'s' if n != 1 else ''}"
            if check.last_diagnosis is not None:
                what += f" and the diagnosis of version {check.diagnosed_version}"
            return (check, inputs, Snapshot(check.history, cmp, check.last_diagnosis, check.diagnosed_version,
                                            "restore", f"restored {what}; version {v.index} ({v.label}) is current: "
                                            f"{_errors_text(v.misfit)}"))

        return work

    def _need_check(self):
        if self.check is None or self.snapshot is None:
            raise ElastoidError("identify a model first")
        return self.check

    def apply(self, result) -> Snapshot:
        """Take a finished work's result (on the GUI thread)."""
        check, inputs, snap = result
        self.check, self.inputs, self.snapshot = check, inputs, snap
        return snap


# ---------------------------------------------------------------------------
# text and arrays for the panel
# ---------------------------------------------------------------------------


def _errors_text(misfit: dict) -> str:
    f, u = misfit.get("force_rms_N"), misfit.get("displacement_rms_px")
    parts = []
    if f is not None:
        parts.append(f"force misfit {f:.4f} N")
    if u is not None:
        parts.append(f"displacement misfit {u:.3f} px")
    return ", ".join(parts)


# a parameter's value below this is shown as 0, and a change from it has no percentage
ZERO = 1e-6


def _num(v: float) -> str:
    if v is None or not isinstance(v, (int, float)) or not math.isfinite(v):
        return "-"
    a = abs(v)
    if a < ZERO:  # a fit at its bound (no relaxation: g1 9e-12) reads as what it is
        return "0"
    if a >= 100:
        return f"{v:.1f}"
    if a >= 1:
        return f"{v:.2f}"
    return f"{v:.3g}"


def parameters_text(parameters: dict, inclusion: dict | None = None, only: tuple | None = None) -> str:
    """'E_B 17.5, E_A 61.4 kPa; g1 0.346, tau1_s 2.00' (moduli first; ``only``: names to keep)."""
    moduli = [(k, v) for k, v in parameters.items() if k.startswith("E_") and k.endswith("_kPa")]
    other = [(k, v) for k, v in parameters.items() if not (k.startswith("E_") and k.endswith("_kPa"))
             and isinstance(v, (int, float))]
    if only is not None:
        moduli = [(k, v) for k, v in moduli if k in only]
        other = [(k, v) for k, v in other if k in only]
    out = []
    if moduli:
        out.append(", ".join(f"{k[2:-4]} {_num(v)}" for k, v in moduli) + " kPa")
    if other:
        out.append(", ".join(f"{k} {_num(v)}" for k, v in other))
    if inclusion:
        out.append(f"inclusion {inclusion.get('name', '')} at {place_text(inclusion)}"
                   f"{' (place uncertain)' if inclusion.get('also_fits') else ''}")
    return "; ".join(out)


def key_parameters(candidate) -> str:
    """A candidate's own parameters first (the effect's), then the moduli it refitted."""
    from app.core.effects import INFO

    if not candidate.parameters:
        return "-"
    own = tuple(p.name for p in INFO[candidate.effect].parameters) if candidate.effect in INFO else ()
    inc = candidate.inclusion if candidate.effect == "inclusion" else None
    first = parameters_text(candidate.parameters, None, own) if own else ""
    moduli = parameters_text(candidate.parameters, inc, tuple(k for k in candidate.parameters if k.startswith("E_")))
    return "; ".join(x for x in (first, moduli) if x)


@dataclass(frozen=True)
class Outline:
    """A region the Compare maps outline: the model's own regions, and the
    inclusion the last diagnosis located (with where it would also fit), until
    it is added."""

    region: Any  # app.core.geometry.Region
    kind: str  # "region" (the model's) | "located" (by the diagnosis) | "also fits"
    label: str  # written on the map beside the outline


def outline_shapes(snapshot) -> list[Outline]:
    """What the Compare maps outline for ``snapshot``: every region of the compared
    model but the background; and, when the diagnosis of the current version found
    an inclusion (a positive, material score) that the model has not got, the located
    sphere and the sphere that fits nearly as well (``also_fits``), if any."""
    from app.core.effects.inclusion import inclusion_region

    cmp = snapshot.comparison if snapshot is not None else None
    if cmp is None:
        return []
    regions = tuple(cmp.regions)
    out = [Outline(r, "region", r.name) for r in regions if r.kind != "background"]
    d = snapshot.diagnosis
    if d is None or snapshot.history is None or snapshot.diagnosed_version != snapshot.history.current:
        return out
    c = next((c for c in d.candidates if c.effect == "inclusion"), None)
    if c is None or not c.inclusion or not (c.fitted and c.score > 0 and c.material):
        return out
    inc = c.inclusion
    if inc["name"] in {r.name for r in regions}:
        return out
    out.append(Outline(inclusion_region(inc), "located", f"{inc['name']}?"))
    also = inc.get("also_fits")
    if also:
        out.append(Outline(inclusion_region({"name": f"{inc['name']} (also fits)", **also}), "also fits",
                           f"{inc['name']}? also"))
    return out


def frame_outlines(snapshot, k: int, frame: str) -> dict:
    """The outlines of :func:`outline_shapes` on frame ``k`` of the snapshot's
    comparison (app.core.compare.outlines), by region name: the model's regions
    as the comparison outlined them (on the worker thread), the diagnosis'
    spheres now (milliseconds)."""
    cmp = snapshot.comparison
    lines = dict(cmp.outlines(k, None, frame))
    extra = [o.region for o in outline_shapes(snapshot) if o.kind != "region"]
    if extra:
        lines.update(cmp.outlines(k, extra, frame))
    return lines


# how far apart (px of the map, x and y) two outline labels' anchors must be for the
# second to stay where the first choice puts it: about a short label's box
LABEL_CLEAR_PX = (24.0, 14.0)


def label_place(parts: list, taken: list, roi_top: float) -> tuple[np.ndarray, tuple[float, float]]:
    """Where to name an outline (``parts``: its polylines, (n, 2) of (col, row)) on a
    map: the point and the label's anchor. Above its top (the image's rows grow
    downwards), or below the top when the ROI's top edge (``roi_top``) cuts it;
    when a label already placed (``taken``: their points) is that close, below its
    bottom, left of it or right of it, the first that is clear. An inclusion found
    inside a region has its top near the region's, and the two names sat on one
    another (blind seed 19007's soft core inside A, 2026-11-29)."""
    pts = np.vstack(parts)
    top, bottom = pts[np.argmin(pts[:, 1])], pts[np.argmax(pts[:, 1])]
    left, right = pts[np.argmin(pts[:, 0])], pts[np.argmax(pts[:, 0])]
    options = [(top, (0.5, 0.0 if top[1] < roi_top + 12 else 1.0)), (bottom, (0.5, 0.0)), (left, (1.0, 0.5)),
               (right, (0.0, 0.5))]
    dx, dy = LABEL_CLEAR_PX
    for point, anchor in options:
        if all(abs(point[0] - q[0]) > dx or abs(point[1] - q[1]) > dy for q in taken):
            return point, anchor
    return options[0]


def outlines_note(shapes: list[Outline], drawn, where=None) -> str:
    """The maps' legend for the outlines, and which of them have none in this
    frame's ROI (``drawn``: the names outlined), each with where it lies
    (``where(region)``, e.g. app.core.compare.outside_text) when given."""
    if not shapes:
        return ""
    words = {"region": "{n}", "located": "{n}, the inclusion the diagnosis located (dashed)",
             "also fits": "{n}, where it would fit nearly as well (dotted)"}
    said = [words[s.kind].format(n=s.label) for s in shapes]
    missing = [f"{s.label} ({where(s.region)})" if where else s.label for s in shapes if s.region.name not in drawn]
    text = "Outlines: " + "; ".join(said) + "."
    if missing:
        text += f" Not drawn: {', '.join(missing)}."
    return text


def score_text(score: float) -> str:
    return "could not be fitted" if not math.isfinite(score) else f"{score:+.1f}"


EVIDENCE_HEAD_CHARS = 120


def evidence_head(text: str, limit: int = EVIDENCE_HEAD_CHARS) -> str:
    """The start of a candidate's evidence, for a table cell: its first clause (up
    to the first "; "), cut at a word within ``limit`` characters, with an
    ellipsis when anything was left out (the whole text goes beside the table)."""
    text = text.strip()
    head = text.split("; ", 1)[0]
    if len(head) > limit:
        cut = head[:limit].rsplit(" ", 1)[0]
        head = (cut if len(cut) > limit // 2 else head[:limit]).rstrip(",;:")
    return head if head == text else head + " \u2026"


def diagnosis_rows(diagnosis) -> list[dict]:
    """One row per candidate, ranked: rank, effect, title, score, key parameters,
    evidence (and its head, :func:`evidence_head`), verdict?"""
    from app.core.effects import INFO

    rows = []
    for i, c in enumerate(diagnosis.candidates, 1):
        rows.append({"rank": i, "effect": c.effect, "title": INFO[c.effect].title if c.effect in INFO else "",
                     "score": c.score, "score_text": score_text(c.score), "parameters": key_parameters(c),
                     "evidence": c.explanation or "", "evidence_head": evidence_head(c.explanation or ""),
                     "verdict": c.effect == diagnosis.verdict,
                     "fitted": c.fitted})
    return rows


def verdict_parts(diagnosis) -> tuple[str, str, str, str]:
    """The verdict in words, plain text: (head, the rest, the masked pair's sentence
    or '', the advice or ''), e.g. ('Verdict: viscoelastic', ', time-dependent
    relaxation (Prony series). The force relaxes by 16% ...', '', ''). The advice:
    "Near tie: ..." and "At the probe's contact: ..." (an inclusion verdict where a
    slip fits too), each when there is one. The panel shows the head in bold, and
    the masked pair ("But ..." or "Or ...") and the advice each as a paragraph of
    their own; so does the report (:func:`app.core.export.verdict_html`)."""
    from app.core.effects import INFO

    d = diagnosis
    if d.verdict == "none":
        return "Verdict: none", f". {d.none_text(with_masked=False)}.", d.masked_sentence(), ""
    c = d.candidate(d.verdict)
    ev = c.evidence[:1].upper() + c.evidence[1:] if c.evidence else ""
    ident = (f" Identified with it, from the whole frames and the force: {d.identified_text()} (Add verdict makes "
             "this the new version).") if d.identified else ""
    confirmed = d.confirmation_text()
    confirmed = f" {confirmed[:1].upper()}{confirmed[1:]}." if confirmed else ""
    tie, contact = d.tie_advice(), d.contact_advice()
    advice = " ".join(x for x in (f"Near tie: {tie}." if tie else "",
                                   f"At the probe's contact: {contact}." if contact else "") if x)
    return (f"Verdict: {d.verdict}", f", {INFO[d.verdict].title}. {ev}.{confirmed}{ident}", d.masked_sentence(),
            advice)


def report_data(snapshot) -> dict | None:
    """The model check as plain data for the HTML report (app.core.export): the
    versions with their errors, which one is current, and the last diagnosis.
    None before the first version."""
    h = snapshot.history if snapshot is not None else None
    if h is None or not len(h):
        return None
    versions = history_rows(h)
    for row, v in zip(versions, h.versions):
        row["force_excess_N"] = v.misfit.get("force_excess_N")
        row["displacement_excess_px"] = v.misfit.get("displacement_excess_px")
    out = {"current": h.current, "versions": versions, "diagnosis": None, "maps": report_maps(snapshot)}
    d = snapshot.diagnosis
    if d is not None:
        head, rest, masked, tie = verdict_parts(d)
        out["diagnosis"] = {"version": snapshot.diagnosed_version, "verdict": d.verdict, "head": head, "rest": rest,
                            "masked": masked, "tie": tie, "noise": d.noise.describe(), "seconds": d.seconds,
                            "candidates": [{k: r[k] for k in ("rank", "effect", "title", "score_text", "parameters",
                                                              "evidence", "verdict")} for r in diagnosis_rows(d)]}
    return out


def report_maps(snapshot) -> list[dict]:
    """The current version's residual map of each compared frame, with the Compare
    tab's outlines, as images for the report: [{"rgb", "caption"}]."""
    from app.core.export import residual_map_rgb

    cmp = snapshot.comparison if snapshot is not None else None
    if cmp is None:
        return []
    shapes = outline_shapes(snapshot)
    out = []
    for k, fc in enumerate(cmp.frames):
        lines = frame_outlines(snapshot, k, "target")
        c0, r0 = fc.roi_px[:2]
        drawn = [(p - [c0, r0], o.kind) for o in shapes for p in lines.get(o.region.name, [])]
        rms = fc.difference_rms_px
        shares = ", ".join(f"{n} {100 * v:.0f}%" for n, v in fc.region_share.items())
        caption = (f"{frame_label(fc)}: displacement difference {rms:.2f} px RMS; share of the misfit {shares}. "
                   f"{outlines_note(shapes, set(lines), lambda region, k=k: cmp.outside_text(k, region))}").strip()
        out.append({"rgb": residual_map_rgb(fc.residual_map, fc.target_roi, drawn), "caption": caption})
    return out


def history_rows(history) -> list[dict]:
    from app.core.diagnose import warning_status

    rows = []
    for v in history.versions:
        rows.append({"index": v.index, "label": v.label, "effects": ", ".join(v.effects) or "none",
                     "parameters": parameters_text(v.parameters, v.inclusion),
                     "force_rms_N": v.misfit.get("force_rms_N"),
                     "displacement_rms_px": v.misfit.get("displacement_rms_px"),
                     "chi2": v.misfit.get("chi2"), "note": v.note, "current": v.index == history.current,
                     "parent": v.parent, "warning": v.warning, "status": warning_status(v.warning),
                     "mesh_check": list(v.mesh_check)})
    return rows


def compare_text(history, i: int, j: int) -> str:
    """``history.compare(i, j)`` in words: what was added or removed, the parameters, the errors."""
    c = history.compare(i, j)
    a, b = history.versions[i], history.versions[j]
    lines = [f"Version {i} ({a.label}) -> {j} ({b.label})",
             f"added: {', '.join(c['added']) or 'nothing'}; removed: {', '.join(c['removed']) or 'nothing'}",
             "parameters"]
    for k, (x, y) in c["parameters"].items():
        change = ""
        if isinstance(x, (int, float)) and isinstance(y, (int, float)) and abs(x) >= ZERO:
            change = f"  {100 * (y - x) / x:+.1f}%"
        lines.append(f"  {k:10s} {_num(x):>7s} -> {_num(y):>7s}{change}")
    lines.append(f"errors, RMS (ratio {j} / {i})")
    names = {"force_rms_N": "force N", "displacement_rms_px": "displacement px",
             "displacement_systematic_px": "systematic px", "chi2": "chi2"}
    for k, (x, y, r) in c["errors"].items():
        ratio = f"x{r:.3g}" if r is not None and math.isfinite(r) else "-"
        lines.append(f"  {names.get(k, k):15s} {_num(x):>7s} -> {_num(y):>7s} {ratio}")
    for v in (a, b):
        if v.warning:
            lines.append(f"warning on version {v.index}: {v.warning}")  # the box wraps it at its width
    for v in (a, b) if i != j else (a,):
        if v.mesh_check:
            lines += ["", mesh_check_text(v.mesh_check)]
    return "\n".join(lines)


def mesh_check_text(lines) -> str:
    """A version's mesh check (its head, then app.core.mesh_check.MeshCheck.lines) for
    the History tab's comparison box (which wraps long lines at its width)."""
    head, *rest = lines
    return "\n".join([f"Mesh check of {head}", *rest])


def arrow_segments(points: np.ndarray, vectors: np.ndarray, scale: float = 1.0, head_px: float = 3.0,
                   ) -> tuple[np.ndarray, np.ndarray]:
    """x, y arrays for a line plot drawn with ``connect="pairs"``: a shaft from each
    point along its vector (times ``scale``) and two strokes of an arrow head."""
    p = np.asarray(points, float).reshape(-1, 2)
    v = scale * np.asarray(vectors, float).reshape(-1, 2)
    keep = np.all(np.isfinite(p), 1) & np.all(np.isfinite(v), 1)
    p, v = p[keep], v[keep]
    if len(p) == 0:
        return np.zeros(0), np.zeros(0)
    q = p + v
    n = np.linalg.norm(v, axis=1, keepdims=True)
    u = np.divide(v, n, out=np.zeros_like(v), where=n > 0)
    h = np.minimum(head_px, 0.45 * n)
    c, s = math.cos(math.radians(28)), math.sin(math.radians(28))
    back = -u
    r1 = np.column_stack([c * back[:, 0] - s * back[:, 1], s * back[:, 0] + c * back[:, 1]]) * h
    r2 = np.column_stack([c * back[:, 0] + s * back[:, 1], -s * back[:, 0] + c * back[:, 1]]) * h
    seg = np.stack([p, q, q, q + r1, q, q + r2], axis=1).reshape(-1, 2)
    return seg[:, 0].copy(), seg[:, 1].copy()


def auto_difference_scale(frame, target_px: float) -> float:
    """A scale (1, 2 or 5 x 10^k, at least 1) that draws the larger valid differences (95th
    percentile, tracking outliers left out) at most about ``target_px`` long."""
    keep = np.asarray(frame.valid, bool)
    if getattr(frame, "outlier", None) is not None:
        keep = keep & ~np.asarray(frame.outlier, bool)
    d = np.asarray(frame.difference_px)[keep]
    if len(d) == 0:
        return 1.0
    m = float(np.percentile(np.linalg.norm(d, axis=1), 95))
    if not math.isfinite(m) or m <= 0:
        return 1.0
    raw = target_px / m
    k = 10.0 ** math.floor(math.log10(raw))
    nice = max(f * k for f in (1.0, 2.0, 5.0) if f * k <= raw * 1.001)
    return max(1.0, nice)


def frame_label(fc) -> str:
    """'frame 2 (3.00 mm) vs 0' for a FrameComparison: the target frame, its probe travel, the source."""
    return f"frame {fc.target} ({fc.displacement_mm:.2f} mm) vs {fc.source}"
