"""Image sources: the folder watcher and the simulated source."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

from app.devices.errors import DeviceTimeout
from app.devices.imaging import FolderWatcher
from app.devices.sim import SimulatedImageSource, speckle_render


def _png(path, value, age_s=5.0):
    import imageio.v3 as iio

    iio.imwrite(path, np.full((8, 12), value, np.uint8), extension=".png")
    t = time.time() - age_s
    os.utime(path, (t, t))


def test_folder_watcher_returns_the_newest_complete_image(tmp_path):
    # the settling time is long so that d.png stays unsettled however slow the machine
    # (with 0.5 s, two busy pytest workers once let it settle before the second call)
    _png(tmp_path / "a.png", 10, age_s=90)
    _png(tmp_path / "b.png", 20, age_s=60)
    (tmp_path / "c.png").write_bytes(b"\x89PNG\r\n\x1a\n half written")  # newer, but broken
    os.utime(tmp_path / "c.png", (time.time() - 40, time.time() - 40))
    _png(tmp_path / "d.png", 30, age_s=0)  # newest, but may still be being written
    w = FolderWatcher(tmp_path, settle_s=30.0)
    f = w.frame()
    assert f.pixels.shape == (8, 12) and f.pixels[0, 0] == 20 and f.metadata["path"].endswith("b.png")
    with pytest.raises(DeviceTimeout, match="no complete new image"):
        w.frame(require_new=True, timeout_s=0.05)


def test_folder_watcher_reads_dicom(tmp_path):
    from pydicom.dataset import FileDataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    meta = FileMetaDataset()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.6.1"
    meta.MediaStorageSOPInstanceUID = generate_uid()
    ds = FileDataset(str(tmp_path / "f.dcm"), {}, file_meta=meta, preamble=b"\0" * 128)
    arr = np.arange(60, dtype=np.uint16).reshape(6, 10)
    ds.Rows, ds.Columns = arr.shape
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
    ds.PixelData = arr.tobytes()
    ds.save_as(tmp_path / "f.dcm", enforce_file_format=True)
    t = time.time() - 2
    os.utime(tmp_path / "f.dcm", (t, t))
    f = FolderWatcher(tmp_path, settle_s=0.1).frame()
    np.testing.assert_array_equal(f.pixels, arr)


def test_simulated_source_calls_render_with_the_displacement():
    seen = []

    def render(d):
        seen.append(d)
        return np.full((4, 5), d)

    src = SimulatedImageSource(render, lambda: 1.25)
    f = src.frame()
    assert seen == [1.25] and f.pixels[0, 0] == 1.25 and f.metadata["displacement_mm"] == 1.25
    r = speckle_render((32, 16), spacing_mm=0.5)
    np.testing.assert_array_equal(r(1.0)[:-2], r(0.0)[2:])  # 1 mm = 2 rows up
