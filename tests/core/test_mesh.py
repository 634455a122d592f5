import os
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from app.core.errors import Cancelled
from app.core.geometry import Region
from app.core.mesh import (MeshSettings, build_mesh, conform_probe_outline, dihedral_angles_deg, probe_face_area_mm2,
                           quality, sizing_field)

SIZE = (60.0, 50.0, 40.0)
PROBE = (15.0, 45.0, 21.0, 29.0)  # 30 x 8 mm face
REGIONS = (
    Region("B", "background"),
    Region("S", "sphere", center_mm=(18.0, 14.0, 22.0), radius_mm=7.0),
    Region("K", "box", center_mm=(44.0, 14.0, 20.0), size_mm=(10.0, 10.0, 12.0)),
    Region("C", "cylinder", center_mm=(18.0, 36.0, 18.0), radius_mm=6.0, height_mm=14.0, axis=(0.0, 0.0, 1.0)),
    Region("E", "ellipsoid", center_mm=(44.0, 36.0, 20.0), radii_mm=(8.0, 6.0, 5.0)),
)
SETTINGS = MeshSettings(edge_mm=6.0, probe_edge_mm=2.0)


@pytest.fixture(scope="module")
def mesh():
    return build_mesh(SIZE, PROBE, REGIONS, SETTINGS)


def test_a_scaled_mesh_is_finer_inside_the_regions_too():
    """with_scale refines the regions' automatic sizes with the rest: the simulator's
    truth (0.7) was once finer everywhere but inside the regions, where it had the
    model's own elements. A region size given by the user is scaled once, not twice."""
    from app.core.mesh import _mesh_key, region_edge_mm

    auto = MeshSettings(edge_mm=9.0, probe_edge_mm=2.0)
    fine = auto.with_scale(0.7)
    for r in REGIONS[1:]:
        assert region_edge_mm(r, fine) == pytest.approx(0.7 * region_edge_mm(r, auto))
    given = MeshSettings(edge_mm=9.0, probe_edge_mm=2.0, region_edge_mm=2.5).with_scale(0.7)
    assert (given.region_edge_mm, given.region_scale) == (pytest.approx(1.75), 1.0)
    assert region_edge_mm(REGIONS[1], given) == pytest.approx(1.75)
    # the sizing field at the sphere's centre follows
    sphere = REGIONS[1]
    for settings, want in ((auto, 0.2 * 14.0), (fine, 0.7 * 0.2 * 14.0)):
        P, _, h = sizing_field(SIZE, PROBE, settings, (REGIONS[0], sphere))
        inside = np.linalg.norm(P - np.asarray(sphere.center_mm), axis=1) < 0.5 * sphere.radius_mm
        assert inside.any() and np.allclose(h[inside], want)
    # another mesh under another key (unscaled settings keep their keys: the committed meshes still load)
    assert _mesh_key(SIZE, PROBE, REGIONS, fine) != _mesh_key(SIZE, PROBE, REGIONS, replace(fine, region_scale=1.0))


def test_every_region_kind_is_meshed_with_its_volume(mesh):
    q = quality(mesh, REGIONS)
    for name in ("S", "K", "C", "E", "B"):
        geo = q.region_geometric_volume_mm3[name]
        assert abs(q.region_volume_mm3[name] - geo) / geo < 0.06, (name, q.lines())
    assert q.min_dihedral_deg > 3.0
    assert abs(mesh.tet_volumes_mm3().sum() - np.prod(SIZE)) / np.prod(SIZE) < 1e-3
    assert all(np.all(mesh.tet_volumes_mm3() > 0) for _ in [0])


def test_probe_face_is_resolved_by_many_nodes(mesh):
    """The face outline is imprinted and refined: many vertices lie on it, on its edges too."""
    pn = mesh.probe_nodes()
    assert pn.sum() >= 40
    p = mesh.points_mm[pn]
    x0, x1, y0, y1 = PROBE
    assert np.isclose(p[:, 0].min(), x0) and np.isclose(p[:, 0].max(), x1)
    assert np.isclose(p[:, 1].min(), y0) and np.isclose(p[:, 1].max(), y1)
    # refined under the probe: edges there are shorter than far away
    e = mesh.points_mm[mesh.tets[:, [0, 1]]]
    length = np.linalg.norm(e[:, 0] - e[:, 1], axis=1)
    c = mesh.points_mm[mesh.tets].mean(axis=1)
    near = (c[:, 2] > SIZE[2] - 4) & (np.abs(c[:, 0] - 30) < 15) & (np.abs(c[:, 1] - 25) < 4)
    far = c[:, 2] < 10
    # fTetWild is not deterministic: three fresh meshes gave 0.53, 0.55 and 0.58, and a 0.6 bound
    # failed now and then; without the refinement the ratio is about 1
    assert np.median(length[near]) < 0.7 * np.median(length[far])


def test_the_bonded_face_is_the_probe_face(mesh):
    """The top-face triangles inside the outline tile the probe face exactly: none
    straddles the outline (fTetWild alone left 80-88% of the face bonded)."""
    x0, x1, y0, y1 = PROBE
    assert probe_face_area_mm2(mesh) == pytest.approx((x1 - x0) * (y1 - y0), rel=1e-9)
    q = quality(mesh, REGIONS)
    assert q.probe_face_area_mm2 == pytest.approx(q.probe_face_geometric_mm2, rel=1e-9)


@pytest.mark.parametrize("rect", [(3.3, 7.7, 2.1, 5.9), (2.05, 7.95, 4.0, 4.93), (0.45, 9.55, 1.5, 8.5), (2.5, 7.5, 3.5, 6.5)])
def test_outline_conforming_on_a_grid_that_ignores_it(rect):
    """A structured mesh (six tets per cube) whose grid lines miss the outline: after
    conforming, the face is tiled exactly, no tet is inverted or lost, the volume is
    unchanged, the angles stay bounded and a second pass changes nothing."""
    size = (10.0, 10.0, 4.0)
    V, T, _ = sizing_field(size, (4.0, 6.0, 4.0, 6.0), MeshSettings(edge_mm=1.0, probe_edge_mm=1.0))
    p = V[T]
    neg = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) < 0
    T = T.astype(np.int64)
    T[neg, 1], T[neg, 2] = T[neg, 2].copy(), T[neg, 1].copy()
    labels = np.arange(len(T)) % 2
    V2, T2, L2 = conform_probe_outline(V, T, labels, size, rect)
    from app.core.mesh import TetMesh

    m = TetMesh(V2, T2, L2, ("B", "A"), size, rect)
    assert probe_face_area_mm2(m) == pytest.approx((rect[1] - rect[0]) * (rect[3] - rect[2]), rel=1e-9)
    vol = m.tet_volumes_mm3()
    assert vol.min() > 0 and vol.sum() == pytest.approx(np.prod(size), rel=1e-12)
    assert dihedral_angles_deg(V2, T2).min() > 3.0
    # each child keeps its parent's label: the labelled volumes are unchanged
    before = TetMesh(V, T, labels, ("B", "A"), size, rect).tet_volumes_mm3()
    assert vol[L2 == 1].sum() == pytest.approx(before[labels == 1].sum(), rel=1e-12)
    V3, T3, _ = conform_probe_outline(V2, T2, L2, size, rect)
    assert len(V3) == len(V2) and np.array_equal(T3, T2)


def test_surface_file_region(tmp_path):
    sphere = Region("S", "sphere", center_mm=(20.0, 20.0, 15.0), radius_mm=6.0)
    surf = Region("S", "surface", surface_mesh=sphere.surface(1.0))
    m = build_mesh((40.0, 40.0, 30.0), (10.0, 30.0, 16.0, 24.0), (Region("B", "background"), surf),
                   MeshSettings(edge_mm=6.0, probe_edge_mm=2.5))
    q = quality(m, (Region("B", "background"), surf))
    assert abs(q.region_volume_mm3["S"] / q.region_geometric_volume_mm3["S"] - 1) < 0.06


def test_meshes_are_cached_by_their_inputs(mesh):
    t0 = time.perf_counter()
    again = build_mesh(SIZE, PROBE, REGIONS, SETTINGS)
    assert time.perf_counter() - t0 < 2.0
    assert np.array_equal(again.tets, mesh.tets)
    # other inputs are another mesh: every input is in the key (meshing them here took 54 s of the suite)
    from app.core.mesh import _mesh_key

    key = _mesh_key(SIZE, PROBE, REGIONS, SETTINGS)
    assert _mesh_key(SIZE, PROBE, REGIONS, MeshSettings(edge_mm=6.0, probe_edge_mm=2.0)) == key
    others = [(SIZE, PROBE, REGIONS[:2], SETTINGS),
              (SIZE, PROBE, REGIONS, MeshSettings(edge_mm=12.0, probe_edge_mm=2.0)),
              ((SIZE[0] + 1.0, *SIZE[1:]), PROBE, REGIONS, SETTINGS),
              (SIZE, (PROBE[0] + 1.0, *PROBE[1:]), REGIONS, SETTINGS),
              (SIZE, PROBE, (REGIONS[0], replace(REGIONS[1], radius_mm=6.0), *REGIONS[2:]), SETTINGS)]
    assert len({_mesh_key(*o) for o in others} | {key}) == len(others) + 1


def test_the_simulators_truth_mesh_is_never_a_models_mesh(monkeypatch):
    """The simulator meshes its truth 0.7 times the identification's size, the
    size the mesh check and a diagnosis' confirmation of a thin finding mesh at.
    Under the same key the cache gave them the truth's own mesh (an inverse
    crime, found 2026-12-01); the truth's meshes are cached under a key of their
    own. Its probe face's outline is meshed 0.7 times the finest outline an
    identification uses (a located inclusion's 1.0 mm), not the face's 2.0 mm
    times 0.7, which was coarser than that model (2026-12-01, evening)."""
    from app.core import twin
    from app.core.experiment import read_experiment
    from app.core.mesh import TRUTH, _mesh_key

    assert _mesh_key(SIZE, PROBE, REGIONS, SETTINGS, TRUTH) != _mesh_key(SIZE, PROBE, REGIONS, SETTINGS)
    asked = {}

    class Stop(Exception):
        pass

    def meshed(exp, settings, **kw):
        asked.update(kw, settings=settings)
        raise Stop

    monkeypatch.setattr(twin, "specimen_mesh", meshed)
    with pytest.raises(Stop):
        twin.SpecimenTwin.build(read_experiment(Path(__file__).resolve().parents[2] / "resources" / "demo"),
                                {"B": 18.0, "A": 63.0})
    assert asked.get("kind") == TRUTH
    truth = asked["settings"]  # the demo's automatic sizes: 10 mm, 2.0 mm on the face
    assert (truth.edge_mm, truth.probe_edge_mm, truth.outline_edge_mm) == pytest.approx((7.0, 1.4, 0.7))


def _temp_folder(tmp_path, monkeypatch):
    """Point the temp folder of this process and of the mesher it spawns at ``tmp_path``."""
    import tempfile

    monkeypatch.setenv("TMPDIR", str(tmp_path))
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))


def test_meshing_can_be_cancelled(tmp_path, monkeypatch):
    _temp_folder(tmp_path, monkeypatch)
    cancel = threading.Event()
    threading.Timer(0.5, cancel.set).start()
    t0 = time.perf_counter()
    with pytest.raises(Cancelled):
        build_mesh(SIZE, PROBE, REGIONS, MeshSettings(edge_mm=3.0, probe_edge_mm=1.0), cancel=cancel, use_cache=False)
    assert time.perf_counter() - t0 < 5.0
    assert list(tmp_path.iterdir()) == []  # the mesher's working folder went with it


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="parent-death signal is Linux-only")
def test_the_mesher_dies_with_its_parent(tmp_path):
    """A window killed mid-meshing leaves no fTetWild process behind."""
    script = tmp_path / "parent.py"
    script.write_text(
        "import sys\n"
        f"sys.path.insert(0, {str(Path(__file__).resolve().parents[2])!r})\n"
        "from tests.core.test_mesh import SIZE, PROBE, REGIONS\n"
        "from app.core.mesh import MeshSettings, build_mesh\n"
        "if __name__ == '__main__':\n"
        "    build_mesh(SIZE, PROBE, REGIONS, MeshSettings(edge_mm=2.0, probe_edge_mm=0.8), use_cache=False)\n")
    # its own temp folder: killed with its parent, the mesher leaves its working folder behind
    parent = subprocess.Popen([sys.executable, str(script)],
                              env={**os.environ, "ELASTOID_CACHE_DIR": str(tmp_path), "TMPDIR": str(tmp_path)})
    try:
        child = None
        for _ in range(300):
            kids = Path(f"/proc/{parent.pid}/task/{parent.pid}/children")
            pids = kids.read_text().split() if kids.exists() else []
            # the spawn start method also runs a resource tracker; the mesher is the busy one
            busy = [p for p in pids if "spawn_main" in Path(f"/proc/{p}/cmdline").read_text(errors="ignore")
                    and "resource_tracker" not in Path(f"/proc/{p}/cmdline").read_text(errors="ignore")]
            if busy:
                child = int(busy[0])
                break
            time.sleep(0.1)
        assert child is not None, "the mesher child never started"
        time.sleep(1.0)  # fTetWild running
        parent.kill()
        parent.wait()
        for _ in range(50):
            if not Path(f"/proc/{child}").exists() or "Z" in Path(f"/proc/{child}/stat").read_text().split()[2]:
                break
            time.sleep(0.1)
        else:
            os.kill(child, 9)
            raise AssertionError("the mesher outlived its parent")
    finally:
        if parent.poll() is None:
            parent.kill()


def test_a_mesher_that_dies_at_start_up_is_reported_not_waited_for(tmp_path):
    """A script that meshes at its top level, without a __main__ guard: the
    spawned child runs the script again, fails to start another process during
    its own start-up, and dies before reading what it was given. The parent had
    waited for ever (start() blocked writing the 0.5 MB surface into a pipe it
    holds open itself, before any timeout runs); now it reports the mesher's
    exit and removes its working folder."""
    script = tmp_path / "unguarded.py"
    script.write_text(
        "import sys\n"
        f"sys.path.insert(0, {str(Path(__file__).resolve().parents[2])!r})\n"
        "from tests.core.test_mesh import SIZE, PROBE, REGIONS\n"
        "from app.core.mesh import MeshSettings, build_mesh\n"
        "build_mesh(SIZE, PROBE, REGIONS, MeshSettings(edge_mm=2.0, probe_edge_mm=0.8), use_cache=False)\n")
    temp = tmp_path / "temp"
    temp.mkdir()
    try:
        run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120,
                             env={**os.environ, "ELASTOID_CACHE_DIR": str(tmp_path), "TMPDIR": str(temp)})
    except subprocess.TimeoutExpired:
        raise AssertionError("meshing waited for a mesher that had died") from None
    assert run.returncode != 0
    assert "MeshingError: the mesher stopped unexpectedly (exit code 1)" in run.stderr, run.stderr[-2000:]
    assert list(temp.iterdir()) == []


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="signals as on Linux")
def test_a_mesher_killed_midway_is_reported_with_its_signal(tmp_path, monkeypatch):
    """The kernel's out-of-memory killer ends the mesher with SIGKILL: the error
    says so in words ("exit code -9" told a clinician nothing)."""
    import multiprocessing as mp
    import signal

    from app.core.errors import MeshingError

    _temp_folder(tmp_path, monkeypatch)
    errors = []

    def run():  # fine enough to run for much longer than the second before the kill
        try:
            build_mesh(SIZE, PROBE, REGIONS, MeshSettings(edge_mm=1.2, probe_edge_mm=0.5), use_cache=False)
        except MeshingError as exc:
            errors.append(str(exc))

    worker = threading.Thread(target=run)
    worker.start()
    for _ in range(300):
        if mp.active_children():
            break
        time.sleep(0.1)
    assert mp.active_children(), "the mesher child never started"
    time.sleep(1.0)  # fTetWild running
    os.kill(mp.active_children()[0].pid, signal.SIGKILL)
    worker.join(60)
    assert not worker.is_alive()
    assert len(errors) == 1 and "the mesher stopped unexpectedly (killed by SIGKILL: the system may have run out " \
                                "of memory" in errors[0], errors
    assert list(tmp_path.iterdir()) == []


def test_the_located_inclusions_looser_envelope_keeps_the_geometry(tmp_path, monkeypatch):
    """A diagnosis meshes its located sphere with fTetWild's envelope at
    LOCATED_EPSILON (faster): the sphere keeps its volume, the box its faces and
    the probe its whole face. And the mesher leaves no files behind: fTetWild
    writes a copy of its input surface into its working folder (0.6 MB at paper
    size), and one folder per meshing run had piled up in the temp folder."""
    from app.core.diagnose import LOCATED_EPSILON

    _temp_folder(tmp_path, monkeypatch)

    regions = (Region("B", "background"), Region("I", "sphere", center_mm=(30.0, 25.0, 24.0), radius_mm=8.0))
    m = build_mesh(SIZE, PROBE, regions, MeshSettings(edge_mm=6.0, probe_edge_mm=2.0, epsilon=LOCATED_EPSILON),
                   use_cache=False)
    q = quality(m, regions)
    geo = q.region_geometric_volume_mm3["I"]
    assert abs(q.region_volume_mm3["I"] - geo) / geo < 0.06, q.lines()
    assert abs(m.tet_volumes_mm3().sum() - np.prod(SIZE)) / np.prod(SIZE) < 1e-3
    assert q.min_dihedral_deg > 3.0
    x0, x1, y0, y1 = PROBE
    assert probe_face_area_mm2(m) == pytest.approx((x1 - x0) * (y1 - y0), rel=1e-6)
    assert list(tmp_path.iterdir()) == []


def test_the_demo_opens_with_the_mesh_shipped_with_it(tmp_path, monkeypatch):
    """resources/meshes holds the demo's mesh under its current cache key (a
    change of MESH_VERSION or of the automatic settings orphans it: regenerate it
    then). With an empty cache the demo's mesh is that copy, not a new fTetWild run."""
    import app.core.mesh as M
    from app.core.experiment import read_experiment
    from app.core.mesh import shipped_mesh_path, specimen_mesh
    from app.resources import resource_path

    monkeypatch.setenv("ELASTOID_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(M, "_tetwild", lambda *a, **k: pytest.fail("the demo was meshed again"))
    exp = read_experiment(resource_path("demo"))
    said = []
    mesh = specimen_mesh(exp, progress=said.append)
    assert said == ["mesh loaded from the copy shipped with ElastoID"]
    bundled = [shipped_mesh_path(exp)]
    assert bundled[0] is not None and [p.name for p in tmp_path.glob("meshes/*.npz")] == [bundled[0].name]
    d = np.load(bundled[0])  # its probe outline is conformed on loading, as for any cached mesh
    V, T, _ = conform_probe_outline(d["points"], d["tets"], d["labels"], mesh.size_mm, mesh.probe_rect_mm)
    assert np.array_equal(mesh.points_mm, V) and np.array_equal(mesh.tets, T) and mesh.region_names == ("B", "A")
    said.clear()
    specimen_mesh(exp, progress=said.append)  # now from the cache
    assert said == ["mesh loaded from cache"]


@pytest.mark.parametrize("face, expected", [((40.0, 10.0), 2.0), ((30.0, 14.0), 2.0), ((20.0, 20.0), 2.0),
                                            ((24.0, 8.0), 1.6)])
def test_the_automatic_elements_on_the_probe_face_are_at_most_2_mm(face, expected):
    """A fifth of the face's short side, at most PROBE_EDGE_MAX_MM: the strain
    beside the face's edges grows with the travel, not with the face. A 30 x 14 mm
    face on the paper's phantom got 2.5 mm elements before, and a model error
    (0.58 px beyond the noise at the true moduli) three times the paper face's
    (0.17 px with 2.0 mm): the diagnosis of a phantom with nothing hidden named
    probe-slip (seed 23010)."""
    from app.core.mesh import PROBE_EDGE_MAX_MM, auto_settings

    w, h = face
    rect = (45.0 - w / 2, 45.0 + w / 2, 45.0 - h / 2, 45.0 + h / 2)
    regions = (Region("B", "background"), Region("A", "sphere", center_mm=(45.0, 45.0, 66.0), radius_mm=15.0))
    s = auto_settings((90.0, 90.0, 96.0), rect, regions)
    assert s.probe_edge_mm == pytest.approx(expected) and s.probe_edge_mm <= PROBE_EDGE_MAX_MM
    assert s.edge_mm == 10.0


def test_the_outline_size_refines_beside_the_face_outline_and_not_inside_the_face():
    """``outline_edge_mm``: the bonded face's edges are where the model's error is
    largest (bench/mesh_field_error.py), so the size there can be set below the
    face's own. The target size is the outline size on the outline, grows at the
    grading's rate from it, and stays the face's own inside the face away from
    the outline; settings without it keep their cache keys (the shipped meshes)."""
    from app.core.mesh import _mesh_key

    face = MeshSettings(edge_mm=6.0, probe_edge_mm=2.0)
    outlined = replace(face, outline_edge_mm=1.5)
    P, _, h0 = sizing_field(SIZE, PROBE, face)
    _, _, h1 = sizing_field(SIZE, PROBE, outlined)
    x0, x1, y0, y1 = PROBE
    inside = (P[:, 0] >= x0) & (P[:, 0] <= x1) & (P[:, 1] >= y0) & (P[:, 1] <= y1)
    to_outline = np.where(inside, np.minimum.reduce([P[:, 0] - x0, x1 - P[:, 0], P[:, 1] - y0, y1 - P[:, 1]]),
                          np.hypot(np.maximum(np.maximum(x0 - P[:, 0], P[:, 0] - x1), 0),
                                   np.maximum(np.maximum(y0 - P[:, 1], P[:, 1] - y1), 0)))
    d = np.hypot(to_outline, SIZE[2] - P[:, 2])
    assert np.all(h1 <= h0 + 1e-12)
    assert np.allclose(h1, np.minimum(h0, 1.5 + face.grading * d))
    near = d <= 1.0 + 1e-9  # the background grid's points nearest the outline (2 mm apart here)
    assert near.any() and np.all(h1[near] <= 1.5 + face.grading * 1.0) and np.all(h0[near] >= 2.0)
    deep_inside = inside & (np.isclose(P[:, 2], SIZE[2])) & (to_outline > 1.5)
    assert deep_inside.any() and np.allclose(h1[deep_inside], 2.0)
    assert (outlined.with_scale(0.5).outline_edge_mm, face.with_scale(0.5).outline_edge_mm) == (0.75, None)
    regions = REGIONS[:2]
    keys = {_mesh_key(SIZE, PROBE, regions, s) for s in (face, outlined, replace(face, outline_edge_mm=1.0))}
    assert len(keys) == 3
