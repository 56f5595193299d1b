"""File → Project status…: `tracemap info` in a window (`engine.project_report`): what the project holds,
which inputs are missing or changed, which results are older than the traces, and the next step."""

from __future__ import annotations

from html import escape

from PySide6.QtCore import Qt
from PySide6.QtWidgets import QDialog, QTextBrowser, QVBoxLayout, QWidget

from engine.project_report import project_report, report_lines
from tracemap_gui.session import Session


def show_status(parent: QWidget, session: Session) -> QDialog:
    """A non-modal report of the open project; it deletes itself when closed."""
    dialog = QDialog(parent)
    dialog.setObjectName("project-status-dialog")
    dialog.setWindowTitle("Project status")
    text = QTextBrowser(dialog)
    text.setObjectName("project-status")
    lines = report_lines(project_report(session.project)) if session.is_open else ["no project is open"]
    text.setHtml("".join(f"<p style='margin:2px'>{'<b>' if line.startswith('next:') else ''}{escape(line)}</p>"
                         for line in lines))
    QVBoxLayout(dialog).addWidget(text)
    dialog.resize(640, 360)
    dialog.setAttribute(Qt.WidgetAttribute.WA_DeleteOnClose)
    dialog.show()
    return dialog
