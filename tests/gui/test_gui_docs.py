"""The documentation's screenshots come from the current code.

docs/screenshots.py drives the real window (on the X display pytest-xvfb
provides, where the 3-D view works) into a temporary folder, on the small test
experiments instead of the demo to stay quick. Every image README.md and
docs/*.md show from docs/images/ must be among the ones it writes, committed,
and of the size it writes them at; and it writes none that the docs do not show.
"""

from __future__ import annotations

import os
import re
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
from conftest import ROOT

IMAGES_DIR = ROOT / "docs" / "images"
IMAGE_REF = re.compile(r"!\[[^\]]*\]\(\s*<?([^)>\s]+\.png)>?[^)]*\)|<img[^>]*\ssrc=[\"']([^\"']+\.png)[\"']", re.I)
PANELS = {"welcome.png", "images.png", "mesh.png", "identification.png", "rig.png", "log.png",
          "modelcheck-compare.png", "modelcheck-diagnosis.png", "modelcheck-history.png"}


def referenced_images() -> dict[str, list[str]]:
    """docs/images/ file name -> the documents that show it."""
    out: dict[str, list[str]] = {}
    for md in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for m in IMAGE_REF.finditer(md.read_text(encoding="utf-8")):
            ref = m.group(1) or m.group(2)
            if "://" in ref:
                continue
            path = (md.parent / ref).resolve()
            assert path.parent == IMAGES_DIR.resolve(), f"{md.name}: images live in docs/images/, not {ref}"
            out.setdefault(path.name, []).append(md.name)
    return out


def png_size(path: Path) -> tuple[int, int]:
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n", f"{path} is not a PNG"
    return struct.unpack(">II", head[16:24])


def test_every_panel_is_shown_in_the_user_guide():
    refs = referenced_images()
    missing = PANELS - {name for name, docs in refs.items() if "user-guide.md" in docs}
    assert not missing, f"the user guide shows no screenshot of {sorted(missing)}"
    assert any("README.md" in docs for docs in refs.values()), "README.md shows no screenshot"


def test_docs_screenshots_come_from_the_current_code(tiny_experiment, visco_experiment, tmp_path):
    from PIL import Image

    assert os.environ.get("DISPLAY"), "the screenshots need an X display (install xvfb for pytest-xvfb)"
    temp = tmp_path / "temp"  # the script's own temp folder: it must leave it empty
    temp.mkdir()
    env = dict(os.environ, QT_QPA_PLATFORM="xcb", TMPDIR=str(temp))  # a real X platform: the 3-D view renders
    env.pop("ELASTOID_NO_3D", None)
    out = tmp_path / "images"
    cmd = [sys.executable, str(ROOT / "docs" / "screenshots.py"), "--out", str(out),
           "--experiment", str(tiny_experiment), "--mesh", "10,3", "--starts", "10,30,60", "--max-evaluations", "60",
           "--visco", str(visco_experiment), "--visco-mesh", "10,3", "--candidates", "viscoelastic,probe-slip"]
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    tail = "\n".join((proc.stdout + proc.stderr).splitlines()[-40:])
    assert proc.returncode == 0, f"docs/screenshots.py failed (exit {proc.returncode}):\n{tail}"
    assert list(temp.iterdir()) == [], "docs/screenshots.py left files in the temp folder"
    produced = {p.name for p in out.glob("*.png")}
    refs = referenced_images()
    assert set(refs) <= produced, f"shown in the docs but not written by docs/screenshots.py: " \
                                  f"{sorted(set(refs) - produced)}\n{tail}"
    committed = {p.name for p in IMAGES_DIR.glob("*.png")}
    assert committed == produced, f"docs/images/ differs from what the script writes: " \
                                  f"extra {sorted(committed - produced)}, missing {sorted(produced - committed)}"
    for name in sorted(produced):
        assert png_size(IMAGES_DIR / name) == png_size(out / name), f"{name}: the committed size differs"
        with Image.open(out / name) as im:
            rgb = np.asarray(im.convert("RGB"), float)
        # something drawn, not a blank or half-laid-out window
        assert rgb.std() > 20 and len(np.unique(rgb.reshape(-1, 3), axis=0)) > 32, name
    # the 3-D view is painted into the mesh screenshot (more than the panel's grey placeholder)
    with Image.open(out / "mesh.png") as im:
        right = np.asarray(im.convert("RGB"))[200:600, 500:1200]
    assert len(np.unique(right.reshape(-1, 3), axis=0)) > 64


LINK = re.compile(r"\]\(\s*<?([^)>\s]*)>?\)")


def test_help_shows_the_guides_and_their_links_lead_somewhere(window, qtbot):
    """Help > User guide opens docs/user-guide.md in a window of its own, with the
    screenshots scaled to the page. In every guide it lists, each link within the
    page scrolls to its heading (Qt names no anchors: the guide matches GitHub's),
    each link to another guide opens it (Back returns), and a guide that is not
    there says so instead of failing."""
    from PySide6.QtCore import QUrl
    from PySide6.QtGui import QTextDocument

    from app.gui.guide import GUIDES, heading_anchor

    assert heading_anchor("7. Model check: compare, diagnose, add an effect") == \
        "7-model-check-compare-diagnose-add-an-effect"
    assert heading_anchor("Where the model check stops") == "where-the-model-check-stops"
    window.act_guide.trigger()
    gw = window.guide_window
    qtbot.waitExposed(gw)
    b = gw.browser
    assert b.source().toLocalFile() == str(ROOT / "docs" / "user-guide.md")
    assert set(gw.pages) == set(GUIDES)  # the source tree has them all
    doc, room = b.document(), b.viewport().width()
    widths = []
    block = doc.begin()
    while block.isValid():
        it = block.begin()
        while not it.atEnd():
            fmt = it.fragment().charFormat()
            if fmt.isImageFormat():
                img = fmt.toImageFormat()
                assert not doc.resource(QTextDocument.ImageResource, QUrl(img.name())).isNull(), img.name()
                widths.append(img.width())
            it += 1
        block = block.next()
    assert len(widths) == len(referenced_images_in(ROOT / "docs" / "user-guide.md"))
    assert 0 < max(widths) <= room

    for name in GUIDES:
        assert gw.show_guide(name), name
        text = (ROOT / "docs" / name).read_text(encoding="utf-8")
        text = re.sub(r"`[^`\n]*`", "", re.sub(r"```.*?```", "", text, flags=re.S))  # code is not linked
        for target in LINK.findall(text):
            if target.startswith("#"):
                assert b.scroll_to_heading(target[1:]), f"{name}: no heading for the link {target}"
                bar = b.verticalScrollBar()  # the heading at the top of the view, or the page's end in view
                assert b.cursorRect().top() <= 5 or bar.value() == bar.maximum(), (name, target)
            elif "://" not in target and not target.startswith("mailto:"):
                path = ROOT / "docs" / target.split("#")[0]
                assert path.is_file(), f"{name}: links to {target}, which is not there"

    gw.show_guide("user-guide.md")
    b.follow(QUrl("experiment-format.md"))
    assert b.source().toLocalFile().endswith("experiment-format.md") and gw.back.isEnabled()
    gw.back.click()
    assert b.source().toLocalFile().endswith("user-guide.md")
    b.follow(QUrl("#8-the-rig"))
    assert b.verticalScrollBar().value() > 0 and b.textCursor().block().text() == "8. The rig"
    # a resize keeps the heading at the top (the text reflows and the screenshots are refitted)
    b.follow(QUrl("#7-model-check-compare-diagnose-add-an-effect"))
    heading = b.textCursor().block()
    for width in (700, 1200, 960):
        gw.resize(width, gw.height())
        qtbot.wait(20)
        top = doc.documentLayout().blockBoundingRect(heading).top()
        assert abs(top - b.verticalScrollBar().value()) <= 2, (width, top, b.verticalScrollBar().value())
    b.follow(QUrl("no-such-guide.md"))
    assert "no-such-guide.md is not in this installation" in gw.note.text()
    assert b.source().toLocalFile().endswith("user-guide.md")
    gw.find_box.setText("ELASTOID_MEMORY_GB")
    assert gw.find_next() and b.textCursor().selectedText() == "ELASTOID_MEMORY_GB"
    gw.find_box.setText("no such words in the guide")
    assert not gw.find_next() and "is not on this page" in gw.note.text()
    window.act_guide.trigger()
    assert window.guide_window is gw  # one window, shown again


def referenced_images_in(md: Path) -> list[str]:
    return [m.group(1) or m.group(2) for m in IMAGE_REF.finditer(md.read_text(encoding="utf-8"))]
