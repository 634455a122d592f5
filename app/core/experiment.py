"""Experiment folders, format 1: read, validate, write.

An experiment is a folder holding ``experiment.toml``, ``force.csv``,
``images/`` and optionally ``regions/``. Units: mm, N, s, kPa. Every defect
raises :class:`ExperimentError` naming the file and the field. ElastoID never
changes an experiment in place: :func:`write_experiment` writes a new folder
(or replaces ``experiment.toml`` atomically while a recording grows).
"""

from __future__ import annotations

import math
import os
import tempfile
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from app.core.errors import ExperimentError
from app.core.geometry import REGION_KINDS, Region

FORMAT = "elastoid-experiment/1"
TOML = "experiment.toml"


@dataclass(frozen=True)
class Specimen:
    size_mm: tuple[float, float, float]
    regions: tuple[Region, ...]
    shape: str = "box"

    @property
    def region_names(self) -> tuple[str, ...]:
        return tuple(r.name for r in self.regions)

    def with_region(self, region: Region) -> "Specimen":
        """A new specimen with ``region`` replacing the one of that name, or appended."""
        names = self.region_names
        if region.name in names:
            regs = tuple(region if r.name == region.name else r for r in self.regions)
        else:
            regs = self.regions + (region,)
        return replace(self, regions=regs)


@dataclass(frozen=True)
class Probe:
    face_mm: tuple[float, float] = (40.0, 10.0)
    center_mm: tuple[float, float] = (45.0, 45.0)
    lateral_axis: tuple[float, float, float] = (1.0, 0.0, 0.0)

    def face_rect_mm(self) -> tuple[float, float, float, float]:
        """(x0, x1, y0, y1) of the face footprint, for an axis-aligned lateral axis."""
        lat = np.abs(np.asarray(self.lateral_axis, float))
        w, e = self.face_mm
        hx, hy = (w / 2, e / 2) if lat[0] >= lat[1] else (e / 2, w / 2)
        cx, cy = self.center_mm
        return (cx - hx, cx + hx, cy - hy, cy + hy)


@dataclass(frozen=True)
class Imaging:
    pixel_spacing_mm: tuple[float, float]  # lateral (per column), depth (per row)
    probe_face_px: tuple[float, float]  # (column, row) of the face centre
    elevation_thickness_mm: float | None = None
    roi_px: tuple[int, int, int, int] | None = None  # col0, row0, col1, row1 (exclusive)


@dataclass(frozen=True)
class Frame:
    image: str
    time_s: float
    displacement_mm: float
    force_N: float | None = None


@dataclass(frozen=True)
class ForceLog:
    time_s: np.ndarray
    displacement_mm: np.ndarray
    force_N: np.ndarray

    def __len__(self) -> int:
        return len(self.time_s)

    def force_at(self, t_s: float) -> float:
        return float(np.interp(t_s, self.time_s, self.force_N))


@dataclass(frozen=True)
class Experiment:
    name: str
    specimen: Specimen
    probe: Probe
    imaging: Imaging
    frames: tuple[Frame, ...]
    force_log: ForceLog
    notes: str = ""
    force_log_file: str = "force.csv"
    reference: dict = field(default_factory=dict)
    path: Path | None = None  # folder it was read from; images are relative to it

    # ---- derived -------------------------------------------------------
    def frame_force_N(self, i: int) -> float:
        f = self.frames[i]
        return f.force_N if f.force_N is not None else self.force_log.force_at(f.time_s)

    def image(self, i: int) -> np.ndarray:
        """Frame i as float64 grey levels (rows = depth, columns = lateral)."""
        from app.core.images import load_image

        return load_image(self.path / self.frames[i].image)

    def reference_moduli_kPa(self, nu: float = 0.49) -> dict[str, float]:
        """Independent reference moduli, converting a shear modulus with E = 2 (1 + nu) G."""
        ref = self.reference or {}
        if "youngs_modulus_kPa" in ref:
            return {k: float(v) for k, v in ref["youngs_modulus_kPa"].items()}
        if "shear_modulus_kPa" in ref:
            return {k: 2.0 * (1.0 + nu) * float(v) for k, v in ref["shear_modulus_kPa"].items()}
        return {}

    def with_frames(self, frames) -> "Experiment":
        return replace(self, frames=tuple(frames))


# ---------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------


class _Fields:
    """Typed access to a TOML table that reports the file and dotted field."""

    def __init__(self, file: Path, table: dict, prefix: str = ""):
        self.file, self.table, self.prefix = file, table, prefix
        self.used: set[str] = set()

    def name(self, key: str) -> str:
        return f"{self.prefix}{key}" if not self.prefix else f"{self.prefix}.{key}"

    def fail(self, key: str, msg: str):
        raise ExperimentError(self.file, self.name(key), msg)

    def get(self, key: str, default: Any = ..., *, required: bool = True):
        self.used.add(key)
        if key not in self.table:
            if default is not ...:
                return default
            self.fail(key, "is missing")
        return self.table[key]

    def string(self, key, default=...):
        v = self.get(key, default)
        if v is not default and not isinstance(v, str):
            self.fail(key, f"must be a string, got {v!r}")
        return v

    def number(self, key, default=..., *, positive=False, nonneg=False):
        v = self.get(key, default)
        if v is default and default is not ...:
            return v
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            self.fail(key, f"must be a finite number, got {v!r}")
        if positive and v <= 0:
            self.fail(key, f"must be positive, got {v!r}")
        if nonneg and v < 0:
            self.fail(key, f"must not be negative, got {v!r}")
        return float(v)

    def vector(self, key, n, default=..., *, positive=False):
        v = self.get(key, default)
        if v is default and default is not ...:
            return v
        ok = isinstance(v, list) and len(v) == n and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v
        )
        if not ok:
            self.fail(key, f"must be a list of {n} numbers, got {v!r}")
        if positive and any(x <= 0 for x in v):
            self.fail(key, f"must be {n} positive numbers, got {v!r}")
        return tuple(float(x) for x in v)

    def sub(self, key, *, required=True) -> "_Fields | None":
        v = self.get(key, None if not required else ...)
        if v is None:
            return None
        if not isinstance(v, dict):
            self.fail(key, f"must be a table, got {v!r}")
        return _Fields(self.file, v, self.name(key))

    def unknown(self, allowed: set[str]):
        for k in self.table:
            if k not in allowed:
                self.fail(k, f"is not a known field here (known: {', '.join(sorted(allowed))})")


def read_experiment(folder: str | Path, *, check_images: bool = True) -> Experiment:
    """Read and validate an experiment folder (or its experiment.toml, which
    names the folder as well: users give either).

    ``check_images`` opens every frame to check that it exists, decodes, and
    that all frames share one size (and the ROI fits it).
    """
    folder = Path(folder)
    if folder.name == TOML and folder.is_file():
        folder = folder.parent
    toml_path = folder / TOML
    if not folder.exists():
        raise ExperimentError(folder, "", "does not exist")
    if not folder.is_dir():
        raise ExperimentError(folder, "", "is not a folder: an experiment is a folder that holds experiment.toml")
    if not toml_path.is_file():
        raise ExperimentError(toml_path, "", "is missing: an experiment folder holds experiment.toml")
    try:
        data = tomllib.loads(toml_path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ExperimentError(toml_path, "", f"is not valid TOML: {exc}") from None

    top = _Fields(toml_path, data)
    fmt = top.string("format")
    if fmt != FORMAT:
        top.fail("format", f"must be {FORMAT!r}, got {fmt!r}")
    name = top.string("name", folder.name)
    notes = top.string("notes", "")

    specimen = _read_specimen(top.sub("specimen"), folder)
    probe = _read_probe(top.sub("probe"), specimen)
    imaging = _read_imaging(top.sub("imaging"))
    frames = _read_frames(top, toml_path)
    fl = top.sub("force_log")
    fl_file = fl.string("file")
    fl.unknown({"file"})
    force_log = read_force_csv(folder / fl_file)
    reference = _read_reference(top.sub("reference", required=False), specimen)
    top.unknown({"format", "name", "notes", "specimen", "probe", "imaging", "frames", "force_log", "reference"})

    exp = Experiment(
        name=name, notes=notes, specimen=specimen, probe=probe, imaging=imaging, frames=frames,
        force_log=force_log, force_log_file=fl_file, reference=reference, path=folder,
    )
    if check_images:
        _check_images(exp, toml_path)
    return exp


def _read_specimen(sp: _Fields, folder: Path) -> Specimen:
    shape = sp.string("shape", "box")
    if shape != "box":
        sp.fail("shape", f"only 'box' is supported, got {shape!r}")
    size = sp.vector("size_mm", 3, positive=True)
    regs_raw = sp.get("regions")
    if not isinstance(regs_raw, list) or not regs_raw:
        sp.fail("regions", "must be a non-empty array of tables ([[specimen.regions]])")
    regions = []
    for i, raw in enumerate(regs_raw):
        if not isinstance(raw, dict):
            sp.fail(f"regions[{i}]", "must be a table")
        regions.append(_read_region(_Fields(sp.file, raw, f"specimen.regions[{i}]"), i, size, folder))
    names = [r.name for r in regions]
    for i, n in enumerate(names):
        if names.index(n) != i:
            raise ExperimentError(sp.file, f"specimen.regions[{i}].name", f"region name {n!r} is used twice")
    sp.unknown({"shape", "size_mm", "regions"})
    return Specimen(size_mm=size, regions=tuple(regions), shape=shape)


_REGION_FIELDS = {
    "background": set(),
    "sphere": {"center_mm", "radius_mm"},
    "box": {"center_mm", "size_mm"},
    "cylinder": {"center_mm", "radius_mm", "height_mm", "axis"},
    "ellipsoid": {"center_mm", "radii_mm"},
    "surface": {"file"},
}


def _read_region(f: _Fields, index: int, size, folder: Path) -> Region:
    name = f.string("name")
    if not name or not name.replace("_", "").isalnum():
        f.fail("name", f"must be letters, digits or _ (it names the parameter E_<name>_kPa), got {name!r}")
    kind = f.string("kind")
    if kind not in REGION_KINDS:
        f.fail("kind", f"must be one of {', '.join(REGION_KINDS)}, got {kind!r}")
    if (index == 0) != (kind == "background"):
        f.fail("kind", "the first region, and only it, must be the background")
    kw: dict[str, Any] = {}
    if kind in ("sphere", "box", "cylinder", "ellipsoid"):
        kw["center_mm"] = f.vector("center_mm", 3)
    if kind in ("sphere", "cylinder"):
        kw["radius_mm"] = f.number("radius_mm", positive=True)
    if kind == "box":
        kw["size_mm"] = f.vector("size_mm", 3, positive=True)
    if kind == "cylinder":
        kw["height_mm"] = f.number("height_mm", positive=True)
        axis = f.vector("axis", 3, (0.0, 0.0, 1.0))
        if np.linalg.norm(axis) == 0:
            f.fail("axis", "must not be the zero vector")
        kw["axis"] = axis
    if kind == "ellipsoid":
        kw["radii_mm"] = f.vector("radii_mm", 3, positive=True)
    if kind == "surface":
        rel = f.string("file")
        kw["file"] = rel
        kw["surface_mesh"] = load_surface(folder / rel, f.name("file"))
    f.unknown({"name", "kind"} | _REGION_FIELDS[kind])
    region = Region(name=name, kind=kind, **kw)
    outside = region_outside(region, size)
    if outside:
        f.fail("file" if kind == "surface" else "center_mm", outside)
    return region


def region_outside(region: Region, size_mm) -> str | None:
    """Why ``region`` does not fit in a specimen box of ``size_mm``, or None."""
    if region.kind == "background":
        return None
    lo, hi = region.bounds_mm()
    tol = 1e-6
    if np.any(lo < -tol) or np.any(hi > np.asarray(size_mm) + tol):
        sx, sy, sz = size_mm
        return (f"region {region.name!r} reaches outside the specimen box [0,{sx:g}] x [0,{sy:g}] x [0,{sz:g}] mm "
                f"(its bounds are {np.round(lo, 3).tolist()} to {np.round(hi, 3).tolist()})")
    return None


def load_surface(path: Path, field_name: str = "file") -> tuple[np.ndarray, np.ndarray]:
    """A closed triangulated surface (STL, PLY, OBJ, VTK) as (vertices mm, triangles)."""
    if not path.is_file():
        raise ExperimentError(path, field_name, "surface file is missing")
    try:
        import pyvista as pv

        mesh = pv.read(str(path)).extract_surface(algorithm="dataset_surface").triangulate().clean()
    except Exception as exc:  # pyvista/vtk raise many types
        raise ExperimentError(path, field_name, f"cannot be read as a surface: {exc}") from None
    if mesh.n_cells == 0:
        raise ExperimentError(path, field_name, "holds no triangles")
    if mesh.n_open_edges > 0:
        raise ExperimentError(path, field_name, f"is not closed ({mesh.n_open_edges} open edges)")
    faces = mesh.faces.reshape(-1, 4)[:, 1:].astype(np.int64)
    return np.asarray(mesh.points, float), faces


# how far the probe's lateral axis may turn from the specimen's x or y axis: the
# model meshes the face as a rectangle along them (Probe.face_rect_mm), and at 1
# degree the corners of a 40 mm face stand 0.35 mm from it (the automatic mesh's
# edges on the face are 1.6-2 mm long)
MAX_OFF_AXIS_DEG = 1.0


def _read_probe(p: _Fields, specimen: Specimen) -> Probe:
    face = p.vector("face_mm", 2, positive=True)
    center = p.vector("center_mm", 2)
    lat = p.vector("lateral_axis", 3, (1.0, 0.0, 0.0))
    lat_a = np.asarray(lat)
    if np.linalg.norm(lat_a) == 0 or abs(lat_a[2]) > 1e-9:
        p.fail("lateral_axis", f"must be a horizontal, non-zero direction, got {list(lat)}")
    lat = tuple(float(x) for x in lat_a / np.linalg.norm(lat_a))
    off_axis = math.degrees(math.asin(min(1.0, min(abs(lat[0]), abs(lat[1])))))
    if off_axis > MAX_OFF_AXIS_DEG:
        given = [float(v) for v in lat_a]
        p.fail("lateral_axis", f"is {off_axis:.1f} degrees from the specimen's x and y axes ({given}): the model "
                               f"meshes the probe face along x or y, within {MAX_OFF_AXIS_DEG:g} degree, so a "
                               "face turned further would be modelled in the wrong place. Turn the probe (or the "
                               "specimen's axes) so that the image's columns run along x or y")
    p.unknown({"face_mm", "center_mm", "lateral_axis"})
    probe = Probe(face_mm=face, center_mm=center, lateral_axis=lat)
    off = probe_off_top(probe, specimen.size_mm)
    if off:
        p.fail("center_mm", off)
    return probe


def probe_off_top(probe: Probe, size_mm) -> str | None:
    """Why the probe face does not lie on the top face of a box of ``size_mm``, or None."""
    x0, x1, y0, y1 = probe.face_rect_mm()
    sx, sy, _ = size_mm
    if x0 < 0 or y0 < 0 or x1 > sx or y1 > sy:
        return f"the probe face [{x0:g},{x1:g}] x [{y0:g},{y1:g}] mm does not lie on the top face"
    return None


def _read_imaging(im: _Fields) -> Imaging:
    spacing = im.vector("pixel_spacing_mm", 2, positive=True)
    face_px = im.vector("probe_face_px", 2)
    elev = im.number("elevation_thickness_mm", None, positive=True)
    roi = im.get("roi_px", None)
    if roi is not None:
        if not (isinstance(roi, list) and len(roi) == 4 and all(isinstance(x, int) and not isinstance(x, bool) for x in roi)):
            im.fail("roi_px", f"must be 4 whole numbers [col0, row0, col1, row1], got {roi!r}")
        if roi[0] < 0 or roi[1] < 0 or roi[2] <= roi[0] or roi[3] <= roi[1]:
            im.fail("roi_px", f"must satisfy 0 <= col0 < col1 and 0 <= row0 < row1, got {roi!r}")
        roi = tuple(roi)
    im.unknown({"pixel_spacing_mm", "probe_face_px", "elevation_thickness_mm", "roi_px"})
    return Imaging(pixel_spacing_mm=spacing, probe_face_px=face_px, elevation_thickness_mm=elev, roi_px=roi)


def _read_frames(top: _Fields, toml_path: Path) -> tuple[Frame, ...]:
    raw = top.get("frames")
    if not isinstance(raw, list) or len(raw) == 0:
        top.fail("frames", "must be a non-empty array of tables ([[frames]])")
    frames = []
    for i, fr in enumerate(raw):
        if not isinstance(fr, dict):
            top.fail(f"frames[{i}]", "must be a table")
        f = _Fields(toml_path, fr, f"frames[{i}]")
        frame = Frame(
            image=f.string("image"),
            time_s=f.number("time_s", nonneg=True),
            displacement_mm=f.number("displacement_mm"),
            force_N=f.number("force_N", None),
        )
        f.unknown({"image", "time_s", "displacement_mm", "force_N"})
        if frames and frame.time_s < frames[-1].time_s:
            f.fail("time_s", f"frames must be in time order: {frame.time_s:g} s comes after {frames[-1].time_s:g} s")
        frames.append(frame)
    return tuple(frames)


def _read_reference(ref: _Fields | None, specimen: Specimen) -> dict:
    if ref is None:
        return {}
    out: dict[str, Any] = {}
    for key in ("youngs_modulus_kPa", "shear_modulus_kPa"):
        table = ref.get(key, None)
        if table is None:
            continue
        if not isinstance(table, dict):
            ref.fail(key, f"must be a table of region = value, got {table!r}")
        for rname, v in table.items():
            if rname not in specimen.region_names:
                ref.fail(f"{key}.{rname}", f"names no region (regions: {', '.join(specimen.region_names)})")
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
                ref.fail(f"{key}.{rname}", f"must be a positive number in kPa, got {v!r}")
        out[key] = {k: float(v) for k, v in table.items()}
    out["method"] = ref.string("method", "")
    ref.unknown({"youngs_modulus_kPa", "shear_modulus_kPa", "method"})
    return out


def read_force_csv(path: Path) -> ForceLog:
    """Read force.csv: header ``time_s,displacement_mm,force_N``, rows in time order."""
    if not path.is_file():
        raise ExperimentError(path, "", "force log is missing")
    text = path.read_text(encoding="utf-8", errors="replace").splitlines()
    if not text:
        raise ExperimentError(path, "header", "is empty; expected time_s,displacement_mm,force_N")
    header = [h.strip() for h in text[0].split(",")]
    want = ["time_s", "displacement_mm", "force_N"]
    if header[:3] != want:
        raise ExperimentError(path, "header", f"must start with {','.join(want)}, got {text[0]!r}")
    rows = []
    for lineno, line in enumerate(text[1:], start=2):
        if not line.strip():
            continue
        parts = line.split(",")
        if len(parts) < 3:
            raise ExperimentError(path, f"line {lineno}", f"needs 3 values, got {line!r}")
        vals = []
        for col, s in zip(want, parts[:3]):
            try:
                x = float(s)
            except ValueError:
                raise ExperimentError(path, f"line {lineno}, {col}", f"is not a number: {s.strip()!r}") from None
            if not math.isfinite(x):
                raise ExperimentError(path, f"line {lineno}, {col}", f"must be finite, got {s.strip()!r}")
            vals.append(x)
        if rows and vals[0] <= rows[-1][0]:
            raise ExperimentError(path, f"line {lineno}, time_s",
                                  f"time must increase: {vals[0]:g} s after {rows[-1][0]:g} s")
        rows.append(vals)
    if len(rows) < 2:
        raise ExperimentError(path, "rows", f"needs at least 2 samples, got {len(rows)}")
    arr = np.asarray(rows, float)
    return ForceLog(time_s=arr[:, 0], displacement_mm=arr[:, 1], force_N=arr[:, 2])


def _check_images(exp: Experiment, toml_path: Path) -> None:
    from app.core.images import image_shape

    shape0 = None
    for i, fr in enumerate(exp.frames):
        p = exp.path / fr.image
        shape = image_shape(p, field=f"frames[{i}].image", expected_spacing_mm=exp.imaging.pixel_spacing_mm)
        if shape0 is None:
            shape0 = shape
        elif shape != shape0:
            raise ExperimentError(p, f"frames[{i}].image",
                                  f"is {shape[1]} x {shape[0]} px but frame 0 is {shape0[1]} x {shape0[0]} px; all frames must share one size")
    roi = exp.imaging.roi_px
    if roi is not None and shape0 is not None and (roi[2] > shape0[1] or roi[3] > shape0[0]):
        raise ExperimentError(toml_path, "imaging.roi_px",
                              f"{list(roi)} reaches outside the {shape0[1]} x {shape0[0]} px images")


# ---------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------


def experiment_to_toml(exp: Experiment) -> str:
    """The experiment.toml text for ``exp`` (format 1)."""
    import tomli_w

    regions = []
    for r in exp.specimen.regions:
        d: dict[str, Any] = {"name": r.name, "kind": r.kind}
        for key in sorted(_REGION_FIELDS[r.kind]):
            val = getattr(r, key)
            if val is not None:
                d[key] = list(val) if isinstance(val, tuple) else val
        regions.append(d)
    imaging: dict[str, Any] = {
        "pixel_spacing_mm": list(exp.imaging.pixel_spacing_mm),
        "probe_face_px": list(exp.imaging.probe_face_px),
    }
    if exp.imaging.elevation_thickness_mm is not None:
        imaging["elevation_thickness_mm"] = exp.imaging.elevation_thickness_mm
    if exp.imaging.roi_px is not None:
        imaging["roi_px"] = list(exp.imaging.roi_px)
    frames = []
    for f in exp.frames:
        d = {"image": f.image, "time_s": f.time_s, "displacement_mm": f.displacement_mm}
        if f.force_N is not None:
            d["force_N"] = f.force_N
        frames.append(d)
    doc: dict[str, Any] = {
        "format": FORMAT,
        "name": exp.name,
        "notes": exp.notes,
        "specimen": {"shape": exp.specimen.shape, "size_mm": list(exp.specimen.size_mm), "regions": regions},
        "probe": {"face_mm": list(exp.probe.face_mm), "center_mm": list(exp.probe.center_mm),
                  "lateral_axis": list(exp.probe.lateral_axis)},
        "imaging": imaging,
        "frames": frames,
        "force_log": {"file": exp.force_log_file},
    }
    if exp.reference:
        doc["reference"] = {k: v for k, v in exp.reference.items() if v not in ("", None, {})}
    return tomli_w.dumps(doc)


def write_toml_atomic(path: Path, text: str) -> None:
    """Replace ``path`` atomically: a reader sees the old or the new file, never half."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-", suffix=".toml")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; an experiment is meant to be shared
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def force_csv_text(log: ForceLog) -> str:
    lines = ["time_s,displacement_mm,force_N"]
    lines += [f"{t:.6f},{d:.6f},{f:.6f}" for t, d, f in zip(log.time_s, log.displacement_mm, log.force_N)]
    return "\n".join(lines) + "\n"


def new_folder_problem(folder: str | Path, overwrite: bool = False) -> str | None:
    """Why a new experiment cannot be written into ``folder``, or None. Checked
    before anything is computed or recorded, so a long simulation or a recording
    never ends in a refusal: a folder that holds something (unless ``overwrite``),
    a file in its place, or a place where it cannot be created."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        return "is a file, not a folder; choose a new folder"
    if folder.is_dir():
        if any(folder.iterdir()) and not overwrite:
            return "already exists and is not empty; choose a new folder"
        return None if os.access(folder, os.W_OK) else "cannot be written into: permission denied"
    parent = folder.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        return f"cannot be created: {parent} is a file"
    if not os.access(parent, os.W_OK):
        return f"cannot be created: permission denied in {parent}"
    return None


def write_experiment(folder: str | Path, exp: Experiment, images: dict[str, np.ndarray] | None = None,
                     *, overwrite: bool = False) -> Path:
    """Write ``exp`` as a new folder. ``images`` maps relative paths to arrays
    (uint8/uint16 written as PNG, or float in [0, 1] scaled to 8 bit).
    Without ``images`` the frames are copied from ``exp.path``."""
    import shutil

    from app.core.images import save_png

    folder = Path(folder)
    problem = new_folder_problem(folder, overwrite)
    if problem:
        raise ExperimentError(folder, "", problem)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "images").mkdir(exist_ok=True)
    for f in exp.frames:
        dst = folder / f.image
        dst.parent.mkdir(parents=True, exist_ok=True)
        if images is not None and f.image in images:
            save_png(dst, images[f.image])
        elif exp.path is not None and (exp.path / f.image).resolve() != dst.resolve():
            shutil.copyfile(exp.path / f.image, dst)
    for r in exp.specimen.regions:
        if r.kind == "surface" and exp.path is not None:
            dst = folder / r.file
            dst.parent.mkdir(parents=True, exist_ok=True)
            if (exp.path / r.file).resolve() != dst.resolve():
                shutil.copyfile(exp.path / r.file, dst)
    (folder / exp.force_log_file).write_text(force_csv_text(exp.force_log), encoding="utf-8")
    write_toml_atomic(folder / TOML, experiment_to_toml(exp))
    return folder
