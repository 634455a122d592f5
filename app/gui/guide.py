"""Help > User guide: the documentation shipped with ElastoID, read in the window.

The guides are the Markdown files of ``docs/`` (app/resources.py:
``docs_path``), bundled in the installer as they are in the source tree, so a
lab PC without a browser or a network still has them. Qt renders the Markdown
(``QTextBrowser``); this module adds what it leaves out:

- links within a page (``#7-model-check-compare-diagnose-add-an-effect``, the
  GitHub form of a heading) scroll to the heading, since Qt names no anchors;
- links to another guide (``cli.md``) open it here, with Back to return;
  links to the web or to other files go to the system's handler;
- the screenshots are scaled down to the page's width.
"""

from __future__ import annotations

import re
import unicodedata
from pathlib import Path

from PySide6.QtCore import QPoint, QUrl, Signal
from PySide6.QtGui import QAction, QDesktopServices, QKeySequence, QTextCursor, QTextDocument, QTextImageFormat
from PySide6.QtWidgets import (QDialog, QHBoxLayout, QLabel, QLineEdit, QPushButton, QTextBrowser, QVBoxLayout)

from app.resources import docs_path

GUIDES = {"user-guide.md": "User guide", "cli.md": "Command line", "experiment-format.md": "Experiment folder",
          "devices.md": "Devices", "method.md": "Method", "model-check.md": "Model check, in depth"}


def heading_anchor(text: str) -> str:
    """The anchor GitHub gives a heading: lower case, punctuation dropped, spaces
    as hyphens ('7. Model check: compare, ...' -> '7-model-check-compare-...')."""
    text = unicodedata.normalize("NFKC", text).strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


class GuideBrowser(QTextBrowser):
    """A Markdown page of docs/ with in-page anchors, links between the guides,
    and images no wider than the page."""

    missing = Signal(str)  # a link to something this installation does not have

    def __init__(self, parent=None):
        super().__init__(parent)
        self.setOpenLinks(False)
        self.anchorClicked.connect(self.follow)
        self._images: list[int] = []  # the page's image positions (found once per page: a resize only refits)
        self.sourceChanged.connect(self._new_page)

    def open_guide(self, name: str, anchor: str = "") -> bool:
        path = docs_path(name)
        if not path.is_file():
            self.missing.emit(f"{name} is not in this installation ({path})")
            return False
        url = QUrl.fromLocalFile(str(path))
        if self.source().toLocalFile() != str(path):
            self.setSource(url, QTextDocument.MarkdownResource)
        if anchor:
            self.scroll_to_heading(anchor)
        else:
            self.verticalScrollBar().setValue(0)
        return True

    def follow(self, url: QUrl) -> None:
        """A clicked link: a heading of this page, another guide, or the system's handler."""
        if url.scheme() in ("http", "https", "mailto"):
            QDesktopServices.openUrl(url)
            return
        target = self.source().resolved(url) if url.isRelative() else url
        path = Path(target.toLocalFile()) if target.isLocalFile() else None
        if path is None:
            QDesktopServices.openUrl(target)
            return
        if path == Path(self.source().toLocalFile()):
            self.scroll_to_heading(url.fragment())
        elif path.suffix == ".md" and path.parent == docs_path():
            self.open_guide(path.name, url.fragment())
        elif path.exists():
            QDesktopServices.openUrl(target)
        else:
            self.missing.emit(f"{path.name} is not in this installation")

    def headings(self) -> list[tuple[str, int]]:
        """(text, position) of each heading of the page."""
        out, block = [], self.document().begin()
        while block.isValid():
            if block.blockFormat().headingLevel():
                out.append((block.text(), block.position()))
            block = block.next()
        return out

    def scroll_to_heading(self, anchor: str) -> bool:
        """Scroll so that the heading whose GitHub anchor is ``anchor`` is at the top."""
        for text, pos in self.headings():
            if heading_anchor(text) == anchor:
                block = self.document().findBlock(pos)
                top = self.document().documentLayout().blockBoundingRect(block).top()
                self.setTextCursor(QTextCursor(block))
                self.verticalScrollBar().setValue(int(top))
                return True
        return False

    def doSetSource(self, name, type=QTextDocument.UnknownResource) -> None:
        # a page opened by setSource (links, the guide buttons): the old page's image
        # positions mean nothing while the new one loads, and a resize meanwhile refits.
        # (Back does not pass here; its sourceChanged comes before any resize.)
        self._images = []
        super().doSetSource(name, type)

    def _new_page(self, _url=None) -> None:
        self._images, block = [], self.document().begin()
        while block.isValid():
            it = block.begin()
            while not it.atEnd():
                frag = it.fragment()
                if frag.isValid() and frag.charFormat().isImageFormat():
                    self._images.append(frag.position())
                it += 1
            block = block.next()
        self._fit_images()

    def resizeEvent(self, event) -> None:
        # the block at the top of the view, taken before the text reflows to the new width
        top = self._top_block()
        super().resizeEvent(event)
        self._fit_images(top)

    def _top_block(self):
        """(block at the top of the view, how far the view's top is below the block's top)."""
        top = self.cursorForPosition(QPoint(0, 0)).block()
        return top, self.verticalScrollBar().value() - self.document().documentLayout().blockBoundingRect(top).top()

    def _fit_images(self, top=None) -> None:
        """Each image at most the page's width (the screenshots are 1,500 px wide),
        the block at the top of the view kept there."""
        doc = self.document()
        room = max(200, self.viewport().width() - 2 * int(doc.documentMargin()) - 8)
        layout, bar = doc.documentLayout(), self.verticalScrollBar()
        reflowed = top is not None
        top, offset = top if reflowed else self._top_block()
        changed = False
        for pos in self._images:
            cur = QTextCursor(doc)
            cur.setPosition(pos)
            cur.setPosition(pos + 1, QTextCursor.KeepAnchor)
            fmt = cur.charFormat()
            if not fmt.isImageFormat():
                continue
            img = fmt.toImageFormat()
            natural = doc.resource(QTextDocument.ImageResource, QUrl(img.name()))
            w = natural.width() if hasattr(natural, "width") and natural.width() > 0 else 0
            if w:
                want = min(w, room)
                if abs(img.width() - want) > 0.5:
                    new = QTextImageFormat(img)
                    new.setWidth(want)
                    new.setHeight(natural.height() * want / w)
                    cur.setCharFormat(new)
                    changed = True
        if changed or reflowed:
            rect = layout.blockBoundingRect(top)
            bar.setValue(int(rect.top() + min(offset, max(0.0, rect.height() - 1))))


class GuideWindow(QDialog):
    """The guides in a window of their own (not modal: read it beside the panels)."""

    def __init__(self, parent=None):
        super().__init__(parent)
        self.setWindowTitle("ElastoID guides")
        self.resize(960, 780)
        self.browser = GuideBrowser(self)
        self.note = QLabel("")
        self.note.setObjectName("hint")
        self.browser.missing.connect(self.note.setText)
        bar = QHBoxLayout()
        self.back = QPushButton("Back")
        self.back.setEnabled(False)
        self.back.clicked.connect(self.browser.backward)
        self.browser.backwardAvailable.connect(self.back.setEnabled)
        bar.addWidget(self.back)
        self.pages = {}
        for name, title in GUIDES.items():
            if docs_path(name).is_file():
                b = QPushButton(title)
                b.clicked.connect(lambda _=False, n=name: self.show_guide(n))
                self.pages[name] = b
                bar.addWidget(b)
        bar.addStretch(1)
        self.find_box = QLineEdit()
        self.find_box.setPlaceholderText("Find (Enter: next)")
        self.find_box.returnPressed.connect(self.find_next)
        self.find_box.setMaximumWidth(220)
        bar.addWidget(self.find_box)
        lay = QVBoxLayout(self)
        lay.addLayout(bar)
        lay.addWidget(self.browser, 1)
        lay.addWidget(self.note)
        find = QAction(self)
        find.setShortcut(QKeySequence.Find)
        find.triggered.connect(lambda: (self.find_box.setFocus(), self.find_box.selectAll()))
        self.addAction(find)

    def show_guide(self, name: str = "user-guide.md", anchor: str = "") -> bool:
        self.note.setText("")
        return self.browser.open_guide(name, anchor)

    def find_next(self) -> bool:
        """The next match of the find box's text, from the top again after the last one."""
        text = self.find_box.text()
        if not text:
            return False
        if self.browser.find(text):
            self.note.setText("")
            return True
        self.browser.moveCursor(QTextCursor.Start)
        found = self.browser.find(text)
        self.note.setText("" if found else f"'{text}' is not on this page")
        return found
