"""Experiment folders: round trip, and every malformed input gives an
ExperimentError naming the file and the field (never a traceback)."""

from __future__ import annotations

import shutil
import tomllib
from pathlib import Path

import numpy as np
import pytest
import tomli_w
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from app.core.errors import ExperimentError
from app.core.experiment import read_experiment, write_experiment


def make_valid(folder: Path, shape=(64, 48)) -> Path:
    """A minimal valid experiment: two noise frames and a short force log."""
    import imageio.v3 as iio

    folder.mkdir(parents=True, exist_ok=True)
    (folder / "images").mkdir(exist_ok=True)
    rng = np.random.default_rng(0)
    for k in range(2):
        iio.imwrite(folder / f"images/f{k}.png", rng.integers(0, 255, shape, dtype=np.uint8))
    (folder / "force.csv").write_text("time_s,displacement_mm,force_N\n0.0,0.0,0.01\n0.5,0.5,0.3\n1.0,1.0,0.6\n")
    doc = {
        "format": "elastoid-experiment/1",
        "name": "tiny",
        "specimen": {"shape": "box", "size_mm": [30.0, 30.0, 20.0],
                     "regions": [{"name": "B", "kind": "background"},
                                 {"name": "A", "kind": "sphere", "center_mm": [15.0, 15.0, 10.0], "radius_mm": 4.0}]},
        "probe": {"face_mm": [10.0, 5.0], "center_mm": [15.0, 15.0], "lateral_axis": [1.0, 0.0, 0.0]},
        "imaging": {"pixel_spacing_mm": [0.2, 0.2], "probe_face_px": [23.5, 0.0], "roi_px": [4, 4, 44, 60]},
        "frames": [{"image": "images/f0.png", "time_s": 0.0, "displacement_mm": 0.0},
                   {"image": "images/f1.png", "time_s": 1.0, "displacement_mm": 1.0}],
        "force_log": {"file": "force.csv"},
        "reference": {"youngs_modulus_kPa": {"A": 63.0, "B": 18.0}, "method": "rheometer"},
    }
    (folder / "experiment.toml").write_text(tomli_w.dumps(doc))
    return folder


def edit_toml(folder: Path, fn) -> None:
    p = folder / "experiment.toml"
    doc = tomllib.loads(p.read_text())
    fn(doc)
    p.write_text(tomli_w.dumps(doc))


def write_dicom(path: Path, image: np.ndarray, spacing_row_col) -> None:
    import pydicom
    from pydicom.dataset import FileDataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.6.1"
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = FileDataset(str(path), {}, file_meta=meta, preamble=b"\0" * 128)
    ds.SOPClassUID = meta.MediaStorageSOPClassUID
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    ds.Rows, ds.Columns = image.shape
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.BitsAllocated = ds.BitsStored = 8
    ds.HighBit = 7
    ds.PixelRepresentation = 0
    ds.PixelSpacing = [str(spacing_row_col[0]), str(spacing_row_col[1])]
    ds.PixelData = image.astype(np.uint8).tobytes()
    ds.save_as(str(path), enforce_file_format=True)


def test_round_trip(tmp_path):
    exp = read_experiment(make_valid(tmp_path / "a"))
    assert exp.specimen.region_names == ("B", "A")
    assert exp.reference_moduli_kPa() == {"A": 63.0, "B": 18.0}
    assert exp.frame_force_N(1) == pytest.approx(0.6)
    out = write_experiment(tmp_path / "b", exp)
    again = read_experiment(out)
    assert again.specimen == exp.specimen
    assert again.frames == exp.frames
    assert again.imaging == exp.imaging
    assert np.allclose(again.force_log.force_N, exp.force_log.force_N)
    assert np.array_equal(again.image(0), exp.image(0))


def test_shear_reference_converts_with_poisson_ratio(tmp_path):
    f = make_valid(tmp_path / "a")
    edit_toml(f, lambda d: d.__setitem__("reference", {"shear_modulus_kPa": {"A": 21.0}}))
    assert read_experiment(f).reference_moduli_kPa(nu=0.5) == {"A": pytest.approx(63.0)}


def test_sixteen_bit_png_tiff_and_dicom_frames_load(tmp_path):
    import imageio.v3 as iio
    import tifffile

    f = make_valid(tmp_path / "a")
    rng = np.random.default_rng(1)
    img16 = rng.integers(0, 65535, (64, 48), dtype=np.uint16)
    iio.imwrite(f / "images/f0.png", img16)
    tifffile.imwrite(f / "images/f1.tif", img16)
    write_dicom(f / "images/f2.dcm", (img16 >> 8).astype(np.uint8), (0.2, 0.2))

    def frames(d):
        d["frames"][1]["image"] = "images/f1.tif"
        d["frames"].append({"image": "images/f2.dcm", "time_s": 1.0, "displacement_mm": 1.0})

    edit_toml(f, frames)
    exp = read_experiment(f)
    assert np.array_equal(exp.image(0), img16.astype(float))
    assert np.array_equal(exp.image(1), img16.astype(float))
    assert exp.image(2).shape == (64, 48)


def _set(path, value):
    def fn(d):
        node = d
        for k in path[:-1]:
            node = node[k]
        if value is _DELETE:
            del node[path[-1]]
        else:
            node[path[-1]] = value
    return fn


_DELETE = object()


def _corrupt_image(f: Path):
    (f / "images/f1.png").write_bytes(b"this is not a png")


def _resize_image(f: Path):
    import imageio.v3 as iio

    iio.imwrite(f / "images/f1.png", np.zeros((32, 48), np.uint8))


def _dicom_spacing(f: Path):
    write_dicom(f / "images/f1.dcm", np.zeros((64, 48), np.uint8), (0.3, 0.3))
    edit_toml(f, lambda d: d["frames"][1].__setitem__("image", "images/f1.dcm"))


def _force(text):
    def fn(f: Path):
        (f / "force.csv").write_text(text)
    return fn


BROKEN = [
    # (id, mutation of the toml or the folder, file the error names, field it names)
    ("missing toml", lambda f: (f / "experiment.toml").unlink(), "experiment.toml", ""),
    ("bad toml syntax", lambda f: (f / "experiment.toml").write_text("format = [unclosed"), "experiment.toml", ""),
    ("wrong format", _set(["format"], "something/2"), "experiment.toml", "format"),
    ("missing size", _set(["specimen", "size_mm"], _DELETE), "experiment.toml", "specimen.size_mm"),
    ("size wrong type", _set(["specimen", "size_mm"], "big"), "experiment.toml", "specimen.size_mm"),
    ("negative size", _set(["specimen", "size_mm"], [30.0, -1.0, 20.0]), "experiment.toml", "specimen.size_mm"),
    ("unknown field", _set(["specimen", "colour"], "red"), "experiment.toml", "specimen.colour"),
    ("unknown region kind", _set(["specimen", "regions", 1, "kind"], "torus"), "experiment.toml",
     "specimen.regions[1].kind"),
    ("region outside", _set(["specimen", "regions", 1, "radius_mm"], 40.0), "experiment.toml",
     "specimen.regions[1].center_mm"),
    ("radius as string", _set(["specimen", "regions", 1, "radius_mm"], "4 mm"), "experiment.toml",
     "specimen.regions[1].radius_mm"),
    ("probe off the top", _set(["probe", "center_mm"], [2.0, 15.0]), "experiment.toml", "probe.center_mm"),
    ("probe face turned off the axes", _set(["probe", "lateral_axis"], [1.0, 0.1, 0.0]), "experiment.toml",
     "probe.lateral_axis"),
    ("missing image", _set(["frames", 1, "image"], "images/nothere.png"), "nothere.png", "frames[1].image"),
    ("corrupt image", _corrupt_image, "f1.png", "frames[1].image"),
    ("frames of different sizes", _resize_image, "f1.png", "frames[1].image"),
    ("dicom spacing disagrees", _dicom_spacing, "f1.dcm", "PixelSpacing"),
    ("frames out of order", _set(["frames", 1, "time_s"], -0.5), "experiment.toml", "frames[1].time_s"),
    ("roi outside image", _set(["imaging", "roi_px"], [4, 4, 100, 60]), "experiment.toml", "imaging.roi_px"),
    ("roi inverted", _set(["imaging", "roi_px"], [40, 4, 10, 60]), "experiment.toml", "imaging.roi_px"),
    ("force log missing", lambda f: (f / "force.csv").unlink(), "force.csv", ""),
    ("force header", _force("t,d,F\n0,0,0\n1,1,1\n"), "force.csv", "header"),
    ("force time not monotonic", _force("time_s,displacement_mm,force_N\n0,0,0\n1,1,1\n0.5,1,1\n"), "force.csv",
     "line 4, time_s"),
    ("force NaN", _force("time_s,displacement_mm,force_N\n0,0,0\n1,1,nan\n"), "force.csv", "line 3, force_N"),
    ("force text", _force("time_s,displacement_mm,force_N\n0,0,0\n1,one,1\n"), "force.csv", "line 3, displacement_mm"),
    ("reference unknown region", _set(["reference", "youngs_modulus_kPa", "C"], 3.0), "experiment.toml",
     "reference.youngs_modulus_kPa.C"),
    ("duplicate region", _set(["specimen", "regions", 1, "name"], "B"), "experiment.toml", "specimen.regions[1].name"),
]


@pytest.mark.parametrize("mutate,file,field", [b[1:] for b in BROKEN], ids=[b[0] for b in BROKEN])
def test_broken_folder_names_file_and_field(tmp_path, mutate, file, field):
    f = make_valid(tmp_path / "x")
    if mutate.__code__.co_varnames[:1] == ("d",):
        edit_toml(f, mutate)
    else:
        mutate(f)
    before = {p: p.read_bytes() for p in f.rglob("*") if p.is_file()}
    with pytest.raises(ExperimentError) as info:
        read_experiment(f)
    err = info.value
    assert err.file.endswith(file), (err.file, file)
    assert err.field == field, (err.field, field)
    assert file.split("/")[-1] in str(err) and field in str(err)
    # reading never changes the folder
    assert before == {p: p.read_bytes() for p in f.rglob("*") if p.is_file()}


_values = st.one_of(st.none(), st.booleans(), st.integers(-10**6, 10**6),
                    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=8),
                    st.lists(st.floats(allow_nan=True), max_size=5), st.lists(st.integers(-5, 100), max_size=5),
                    st.dictionaries(st.text(max_size=3), st.integers(), max_size=2))


def _leaves(node, path=()):
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _leaves(v, path + (k,))
    elif isinstance(node, list) and node and isinstance(node[0], dict):
        for i, v in enumerate(node):
            yield from _leaves(v, path + (i,))
    else:
        yield path


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_any_mutated_field_gives_a_clear_error_or_loads(tmp_path_factory, data):
    f = make_valid(tmp_path_factory.mktemp("h"))
    doc = tomllib.loads((f / "experiment.toml").read_text())
    leaves = list(_leaves(doc))
    path = data.draw(st.sampled_from(leaves))
    value = data.draw(_values)
    node = doc
    for k in path[:-1]:
        node = node[k]
    if value is None:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    try:
        text = tomli_w.dumps(doc)
    except Exception:  # not representable in TOML (e.g. NaN is fine, None is not): nothing to test
        return
    (f / "experiment.toml").write_text(text)
    try:
        read_experiment(f)
    except ExperimentError as err:
        assert err.file and str(err)
    shutil.rmtree(f)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rows=st.lists(st.tuples(st.floats(allow_nan=True, allow_infinity=True),
                               st.floats(allow_nan=True), st.floats(allow_nan=True)), max_size=6))
def test_any_force_log_gives_a_clear_error_or_loads(tmp_path_factory, rows):
    from app.core.experiment import read_force_csv

    p = tmp_path_factory.mktemp("csv") / "force.csv"
    p.write_text("time_s,displacement_mm,force_N\n" + "".join(f"{a},{b},{c}\n" for a, b, c in rows))
    try:
        log = read_force_csv(p)
    except ExperimentError as err:
        assert "force.csv" in str(err)
    else:
        assert np.all(np.diff(log.time_s) > 0) and np.all(np.isfinite(log.force_N))


def test_a_new_experiment_folder_is_checked_before_anything_is_written(tmp_path):
    from app.core.experiment import new_folder_problem

    assert new_folder_problem(tmp_path / "new" / "deeper") is None  # created with its parents
    empty = tmp_path / "empty"
    empty.mkdir()
    assert new_folder_problem(empty) is None
    full = tmp_path / "full"
    full.mkdir()
    (full / "old.txt").write_text("kept")
    assert "not empty" in new_folder_problem(full)
    assert new_folder_problem(full, overwrite=True) is None
    a_file = tmp_path / "a_file"
    a_file.write_text("kept")
    assert "is a file, not a folder" in new_folder_problem(a_file)
    assert f"{a_file} is a file" in new_folder_problem(a_file / "sub" / "exp")
    exp = read_experiment(make_valid(tmp_path / "valid"))
    with pytest.raises(ExperimentError, match="is a file, not a folder") as info:
        write_experiment(a_file, exp)
    assert info.value.file == str(a_file)
    assert a_file.read_text() == "kept" and (full / "old.txt").read_text() == "kept"


def test_the_experiment_toml_names_its_folder_and_a_missing_folder_says_so(tmp_path):
    folder = make_valid(tmp_path / "a")
    exp = read_experiment(folder / "experiment.toml")  # was refused: "is not a folder"
    assert exp.path == folder and exp.specimen.region_names == ("B", "A")
    with pytest.raises(ExperimentError, match="does not exist"):
        read_experiment(tmp_path / "nowhere")
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(ExperimentError, match="is not a folder: an experiment is a folder"):
        read_experiment(tmp_path / "notes.txt")


def test_the_probe_may_lie_along_x_or_y_either_way_within_a_degree(tmp_path):
    """A probe turned a quarter or half turn, or by less than a degree, loads (its
    face along y for a quarter turn); one turned further is refused above."""
    for i, (axis, rect_along_y) in enumerate((([0.0, -1.0, 0.0], True), ([-1.0, 0.0, 0.0], False),
                                              ([1.0, 0.015, 0.0], False))):
        f = make_valid(tmp_path / f"x{i}")
        edit_toml(f, _set(["probe", "lateral_axis"], axis))
        probe = read_experiment(f).probe
        x0, x1, y0, y1 = probe.face_rect_mm()
        w, e = probe.face_mm
        assert (y1 - y0, x1 - x0) == pytest.approx((w, e) if rect_along_y else (e, w))
    f = make_valid(tmp_path / "diagonal")
    edit_toml(f, _set(["probe", "lateral_axis"], [0.7071, 0.7071, 0.0]))
    with pytest.raises(ExperimentError, match=r"is 45\.0 degrees from the specimen's x and y axes \(\[0\.7071, 0\.7071, "
                                              r"0\.0\]\)"):
        read_experiment(f)
