"""``elastoid selftest`` from source, in this process: every check passes and
reports what it measured; a failing check is reported and fails the exit code."""

from __future__ import annotations

import re

import pytest

from app import selftest
from app.cli import main


@pytest.fixture
def offscreen(monkeypatch):
    """The window check creates the QApplication (when none exists) on Qt's offscreen platform."""
    monkeypatch.setenv("QT_QPA_PLATFORM", "offscreen")
    monkeypatch.setenv("ELASTOID_NO_3D", "1")


def _detail(results, name):
    (r,) = [r for r in results if r.name == name]
    assert r.passed, r.line()
    return r.detail


def test_every_check_passes_and_measures_what_it_claims(offscreen):
    lines = []
    results = selftest.run(out=lines.append)
    assert [r.name for r in results] == list(selftest.DEFAULT_CHECKS)
    assert lines == [r.line() for r in results]
    failed = [r.line() for r in results if not r.passed]
    assert not failed, "\n".join(failed)
    assert all(line.startswith("PASS ") for line in lines)

    # imports: the packages' modules (~80) and every listed library
    n_app = int(re.search(r"(\d+) app modules", _detail(results, "imports")).group(1))
    assert n_app >= 60
    # the solver: PARDISO where pypardiso is a dependency, a tiny error either way
    solver = _detail(results, "solver")
    assert solver.startswith("pardiso" if selftest._needs_pardiso() else "superlu")
    assert float(re.search(r"error ([0-9.e+-]+)", solver).group(1)) < 1e-8
    # the mesh: a few thousand tets, the sphere's volume within 5 %
    mesh = _detail(results, "mesh")
    nodes, tets, vol, sphere = (float(x) for x in
                                re.search(r"(\d+) nodes, (\d+) tets, inclusion volume (\d+) mm3 \(sphere (\d+)\)",
                                          mesh).groups())
    assert 500 < tets < 20000 and nodes < tets
    assert sphere == pytest.approx(4 / 3 * 3.14159265 * 6.0**3, abs=1.0)
    assert vol == pytest.approx(sphere, rel=0.05)
    # the forward model: positive forces, stiffer inclusion -> more force, plausible magnitude
    f_stiff, f_soft = (float(x) for x in re.search(r"probe force ([0-9.]+) N/mm .*> ([0-9.]+) N/mm",
                                                    _detail(results, "forward")).groups())
    # 12 x 6 mm face on a 24 mm thick 18 kPa block: ~E A / h = 18e-3 N/mm2 * 72 mm2 / 24 mm = 0.05 N/mm,
    # several times more with the bonded face's confinement and near-incompressibility (nu = 0.49)
    assert 0.05 < f_soft < f_stiff < 2.0
    # the off-screen image: drawn, with the inclusion's colour on the cut
    drawn, incl = (float(x) for x in re.search(r"(\d+)% of pixels drawn, inclusion ([0-9.]+)%",
                                               _detail(results, "render")).groups())
    assert drawn > 10 and incl > 0.2
    # the rig over TCP (and ptys here): the move ends at 1 mm, the sensor reads the spring's 0.5 N
    rig = _detail(results, "rig")
    for transport, f in re.findall(r"(socket|pty): GRBL 1\.1h Idle->1\.000 mm, \d+ samples, ([0-9.]+) N", rig):
        assert float(f) == pytest.approx(0.5, abs=0.02), transport
    assert rig.startswith("socket:")
    # the window: built with its docks (images, mesh, identification, rig, log, ...), the demo opened in it
    n_docks = int(re.search(r"offscreen: (\d+) docks, demo opened", _detail(results, "window")).group(1))
    assert n_docks >= 5


def test_a_failing_check_is_reported_and_fails_the_exit_code(monkeypatch, capsys):
    def broken(ctx):
        raise RuntimeError("the thing is missing")

    monkeypatch.setitem(selftest.CHECKS, "resources", broken)
    assert main(["--selftest", "--only", "solver,resources"]) == 1
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("PASS solver")
    assert re.match(r"FAIL resources +\( *\d+\.\d s\) RuntimeError: the thing is missing$", out[1])
    assert out[2].startswith("selftest: 1/2 passed (from source")


def test_forward_without_a_mesh_fails_instead_of_passing(capsys):
    """--only forward runs the mesh check first; without it the forward check must fail, not pass vacuously."""
    results = selftest.run(["forward"], out=lambda line: None)
    assert [(r.name, r.passed) for r in results] == [("forward", False)]
    assert "no mesh" in results[0].detail


def test_unknown_check_is_a_usage_error(capsys):
    assert main(["selftest", "--only", "imports,warp-drive"]) == 2
    assert "unknown check(s): warp-drive" in capsys.readouterr().err


@pytest.mark.parametrize("slivers", [1, 2])
def test_a_sliver_in_one_mesh_is_meshed_again_and_in_two_fails(monkeypatch, slivers):
    """fTetWild is not deterministic: one CI run's mesh of the check's box had a
    sliver of 0.47 deg (25 local runs: 3.8-23 deg). One such mesh is meshed
    again and said so; two in a row fail the check."""
    import dataclasses

    import app.core.mesh as mesh_module

    real, calls = mesh_module.quality, []

    def quality(mesh, regions):
        q = real(mesh, regions)
        calls.append(q)
        return dataclasses.replace(q, min_dihedral_deg=0.47) if len(calls) <= slivers else q

    monkeypatch.setattr(mesh_module, "quality", quality)
    (r,) = selftest.run(["mesh"], out=lambda line: None)
    assert len(calls) == 2
    if slivers == 1:
        assert r.passed and r.detail.endswith("; meshed twice, the first had a sliver of 0.47 deg"), r.line()
    else:
        assert not r.passed and "degenerate tetrahedra in two meshes (min dihedral angles 0.47 and 0.47 deg)" in \
            r.detail, r.line()
