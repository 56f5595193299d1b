"""Fixtures of the GUI tests: a private copy of the quick demo project, a session on it, the image editor."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from PySide6.QtCore import QSettings


@pytest.fixture(scope="session", autouse=True)
def user_settings(tmp_path_factory):
    """Keep the recent-projects list (QSettings) out of the user's home."""
    folder = tmp_path_factory.mktemp("qsettings")
    for fmt in (QSettings.Format.NativeFormat, QSettings.Format.IniFormat):
        QSettings.setPath(fmt, QSettings.Scope.UserScope, str(folder))


@pytest.fixture
def project_path(quick_demo, tmp_path) -> Path:
    """A private copy of the quick demo project (3 photos of 640×480 with their 2D and 3D traces); mtimes
    are kept, so the photos still match their fingerprints."""
    shutil.copytree(quick_demo / "data", tmp_path / "data")
    shutil.copy2(quick_demo / "demo.tracemap", tmp_path / "demo.tracemap")
    return tmp_path / "demo.tracemap"


@pytest.fixture
def session(qapp, project_path):
    from tracemap_gui.session import Session

    s = Session()
    s.open(project_path)
    yield s
    s.close()


@pytest.fixture
def editor(qtbot, session):
    """The image editor on the demo project, shown, with the first photo's pixels loaded."""
    from tracemap_gui.image_editor import ImageEditor

    window = ImageEditor(session)
    qtbot.addWidget(window)
    window.show()
    qtbot.waitExposed(window)
    qtbot.waitUntil(lambda: window.view.pyramid is not None, timeout=10_000)
    yield window
    session.jobs.cancel_all()
    qtbot.waitUntil(lambda: not session.jobs.running, timeout=30_000)


@pytest.fixture
def viewer(qtbot, session):
    """The 3D viewer on a private copy of the quick demo."""
    from tests.gui.flows import open_viewer

    window = open_viewer(qtbot, session)
    yield window
    session.jobs.cancel_all(5000)
    session.close()  # before any event lets pytest-qt delete the window its tools watch
