"""Ultrasound frames: loading (PNG 8/16-bit, TIFF, DICOM) and image geometry.

The image plane is the probe's azimuthal plane and moves with the probe:
column c, row r of a frame taken at probe travel d maps to

    (cx, cy, sz - d) + (c - c0) * sc * lateral_axis - (r - r0) * sr * z

with (sc, sr) = pixel_spacing_mm and (c0, r0) = probe_face_px.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from app.core.errors import ExperimentError

_DICOM_SUFFIXES = {".dcm", ".dicom", ""}


def _is_dicom(path: Path) -> bool:
    if path.suffix.lower() in (".dcm", ".dicom"):
        return True
    try:
        with open(path, "rb") as fh:
            head = fh.read(132)
        return head[128:132] == b"DICM"
    except OSError:
        return False


def _read_dicom(path: Path, field: str):
    try:
        import pydicom

        ds = pydicom.dcmread(str(path))
        arr = ds.pixel_array
    except Exception as exc:
        raise ExperimentError(path, field, f"cannot be read as DICOM: {exc}") from None
    spacing = None
    ps = getattr(ds, "PixelSpacing", None)
    if ps is not None and len(ps) == 2:
        spacing = (float(ps[1]), float(ps[0]))  # DICOM is (row, column) = (depth, lateral)
    return np.asarray(arr), spacing


def _read_raw(path: Path, field: str):
    if not path.is_file():
        raise ExperimentError(path, field, "image file is missing")
    if _is_dicom(path):
        return _read_dicom(path, field)
    try:
        if path.suffix.lower() in (".tif", ".tiff"):
            import tifffile

            arr = tifffile.imread(str(path))
        else:
            import imageio.v3 as iio

            arr = iio.imread(path, plugin="pillow")  # PNG (8 or 16 bit); no guessing among plugins
    except Exception as exc:
        raise ExperimentError(path, field, f"cannot be decoded as an image: {exc}") from None
    return np.asarray(arr), None


def _to_grey(arr: np.ndarray, path: Path, field: str) -> np.ndarray:
    if arr.ndim == 3 and arr.shape[2] in (3, 4):
        arr = arr[..., :3].astype(float).mean(axis=2)
    if arr.ndim != 2 or arr.size == 0:
        raise ExperimentError(path, field, f"must be a 2-D grey image, got shape {arr.shape}")
    return arr.astype(np.float64)


def load_image(path: str | Path, field: str = "image") -> np.ndarray:
    """Frame as float64 grey levels in the file's own scale (0..255 or 0..65535)."""
    path = Path(path)
    arr, _ = _read_raw(path, field)
    return _to_grey(arr, path, field)


def image_shape(path: str | Path, field: str = "image", expected_spacing_mm=None) -> tuple[int, int]:
    """(rows, columns) of an image, after checking it decodes and, for DICOM,
    that its own pixel spacing agrees with ``expected_spacing_mm`` (lateral, depth)."""
    path = Path(path)
    arr, spacing = _read_raw(path, field)
    grey = _to_grey(arr, path, field)
    if spacing is not None and expected_spacing_mm is not None:
        if not np.allclose(spacing, expected_spacing_mm, rtol=1e-3, atol=1e-6):
            raise ExperimentError(
                path, "PixelSpacing",
                f"DICOM pixel spacing (lateral {spacing[0]:g}, depth {spacing[1]:g} mm) disagrees with "
                f"imaging.pixel_spacing_mm {list(expected_spacing_mm)} in experiment.toml")
    return grey.shape


def save_png(path: str | Path, image: np.ndarray) -> None:
    """PNG, 8-bit for uint8 or float in [0, 1], 16-bit for uint16."""
    import imageio.v3 as iio

    img = np.asarray(image)
    if img.dtype == np.uint8 or img.dtype == np.uint16:
        out = img
    else:
        out = np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)
    iio.imwrite(Path(path), out, extension=".png")


# ---------------------------------------------------------------------------
# geometry
# ---------------------------------------------------------------------------


def pixel_to_world(cols: np.ndarray, rows: np.ndarray, exp, displacement_mm: float) -> np.ndarray:
    """World points (n, 3) mm of pixel centres (cols, rows) in a frame taken at
    probe travel ``displacement_mm``."""
    im, pr = exp.imaging, exp.probe
    lat = np.asarray(pr.lateral_axis, float)
    origin = np.array([pr.center_mm[0], pr.center_mm[1], exp.specimen.size_mm[2] - displacement_mm])
    c = (np.asarray(cols, float) - im.probe_face_px[0]) * im.pixel_spacing_mm[0]
    r = (np.asarray(rows, float) - im.probe_face_px[1]) * im.pixel_spacing_mm[1]
    return origin + c[:, None] * lat[None, :] - r[:, None] * np.array([0.0, 0.0, 1.0])


def world_to_pixel(points_mm: np.ndarray, exp, displacement_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`pixel_to_world` for points in the image plane: (cols, rows)."""
    im, pr = exp.imaging, exp.probe
    lat = np.asarray(pr.lateral_axis, float)
    origin = np.array([pr.center_mm[0], pr.center_mm[1], exp.specimen.size_mm[2] - displacement_mm])
    d = np.asarray(points_mm, float) - origin
    cols = d @ lat / im.pixel_spacing_mm[0] + im.probe_face_px[0]
    rows = -d[:, 2] / im.pixel_spacing_mm[1] + im.probe_face_px[1]
    return cols, rows


def default_roi(exp, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """The experiment's ROI, or the image less a 10% margin, clipped to the specimen."""
    if exp.imaging.roi_px is not None:
        return exp.imaging.roi_px
    rows, cols = shape
    mc, mr = cols // 10, rows // 10
    return (mc, mr, cols - mc, rows - mr)
