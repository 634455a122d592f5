"""Image sources: where the ultrasound frames come from.

:class:`ImageSource` has one method, ``frame()``, returning an
:class:`ImageFrame` (2-D array + metadata). :class:`FolderWatcher` takes the
newest complete file a scanner exported into a folder (DICOM, PNG, TIFF); the
simulated source (:class:`app.devices.sim.SimulatedImageSource`) renders one.
"""

from __future__ import annotations

import os
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from app.devices.errors import DeviceError, DeviceTimeout

IMAGE_PATTERNS = ("*.png", "*.dcm", "*.dicom", "*.tif", "*.tiff")


@dataclass(frozen=True)
class ImageFrame:
    pixels: np.ndarray  # 2-D, rows = depth, columns = lateral
    metadata: dict = field(default_factory=dict)


class ImageSource(ABC):
    name = "image source"

    @abstractmethod
    def frame(self) -> ImageFrame:
        """The current frame. Raises DeviceError (or DeviceTimeout) if there is none."""

    def close(self) -> None:
        """Release whatever the source holds."""


def read_image_file(path: Path) -> np.ndarray:
    """A 2-D array from a PNG/TIFF/DICOM file (colour is averaged to grey). Raises DeviceError if unreadable."""
    path = Path(path)
    try:
        if path.suffix.lower() in (".dcm", ".dicom"):
            import pydicom

            arr = np.asarray(pydicom.dcmread(str(path)).pixel_array)
        elif path.suffix.lower() in (".tif", ".tiff"):
            import tifffile

            arr = np.asarray(tifffile.imread(str(path)))
        else:
            import imageio.v3 as iio

            arr = np.asarray(iio.imread(path))
    except Exception as exc:  # the decoders raise many types for a half-written file
        raise DeviceError(f"{path.name} cannot be decoded ({exc})", device="image source") from None
    if arr.ndim == 3 and arr.shape[2] in (3, 4):
        arr = arr[..., :3].mean(axis=2).astype(arr.dtype)
    if arr.ndim != 2 or arr.size == 0:
        raise DeviceError(f"{path.name} is not a 2-D grey image (shape {arr.shape})", device="image source")
    return arr


class FolderWatcher(ImageSource):
    """The newest complete image a scanner exported into ``folder``.

    A file counts as complete once it is at least ``settle_s`` old (by its
    modification time) and decodes. ``frame(require_new=True)`` waits (up to
    ``timeout_s``) for a file newer than the one returned last.
    """

    name = "image folder"

    def __init__(self, folder: str | Path, *, patterns=IMAGE_PATTERNS, settle_s: float = 0.2,
                 timeout_s: float = 2.0):
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise DeviceError(f"{self.folder} is not a folder", device="image source")
        self.patterns = tuple(patterns)
        self.settle_s = settle_s
        self.timeout_s = timeout_s
        self._last: tuple[float, str] | None = None

    def _candidates(self) -> list[tuple[float, Path]]:
        files = []
        for pat in self.patterns:
            for p in self.folder.glob(pat):
                try:
                    files.append((os.stat(p).st_mtime, p))
                except OSError:
                    continue
        files.sort(key=lambda x: (x[0], x[1].name), reverse=True)
        return files

    def frame(self, *, require_new: bool = False, timeout_s: float | None = None) -> ImageFrame:
        timeout_s = self.timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + timeout_s
        while True:
            now = time.time()
            for mtime, path in self._candidates():
                key = (mtime, path.name)
                if require_new and self._last is not None and key <= self._last:
                    break
                if now - mtime < self.settle_s:
                    continue  # still being written, perhaps
                try:
                    arr = read_image_file(path)
                except DeviceError:
                    continue
                self._last = key
                return ImageFrame(arr, {"source": "folder", "path": str(path), "mtime": mtime})
            if time.monotonic() >= deadline:
                what = "new " if require_new else ""
                raise DeviceTimeout(f"no complete {what}image ({', '.join(self.patterns)}) appeared in "
                                    f"{self.folder} within {timeout_s:g} s", device="image source")
            time.sleep(min(0.05, max(0.0, deadline - time.monotonic())))
