"""Edits stored by a worker (`Session.push_in_background`): off the GUI thread, in order, undoable (issue 5)."""

from __future__ import annotations

import gc
import threading
import time
from dataclasses import replace
from pathlib import Path

from engine.project import Project
from engine.traces import Trace2D
from tests.gui.flows import stored_traces2d, stored_traces3d_parents
from tracemap_gui import commands
from tracemap_gui.session import Session

LINE = [[100.0, 100.0], [200.0, 150.0], [300.0, 120.0]]


def re_extraction(session):
    """An extraction's edit: the first two 3D traces replaced by new ones (copies, new ids)."""
    old = session.traces3d()[:2]
    return commands.ReplaceTraces3D(session, old, [replace(t, id=0) for t in old], "Extract 2 3D traces"), old


def watch_writers(monkeypatch, hold: threading.Event | None = None) -> list[threading.Thread]:
    """The threads that open a handle to write through; with `hold`, each waits for it first."""
    threads, for_thread = [], Project.for_thread

    def handle(project):
        threads.append(threading.current_thread())
        if hold is not None:
            hold.wait(10)
        return for_thread(project)

    monkeypatch.setattr(Project, "for_thread", handle)
    return threads


def test_background_edit_is_stored_by_a_worker_then_undoable(session, project_path, qtbot, monkeypatch):
    writers = watch_writers(monkeypatch)
    command, old = re_extraction(session)
    before = stored_traces3d_parents(project_path)
    with qtbot.waitSignal(session.traces3d_changed, timeout=10_000):
        session.push_in_background(command)
    assert writers and threading.main_thread() not in writers
    after = stored_traces3d_parents(project_path)
    new = set(after) - set(before)
    assert len(new) == 2 and not {t.id for t in old} & set(after)
    assert {t.id for t in session.traces3d()} == set(after)  # the cache follows the file
    assert session.undo_stack.count() == 1 and session.undo_stack.undoText() == "Extract 2 3D traces"
    session.undo_stack.undo()
    assert stored_traces3d_parents(project_path) == before
    session.undo_stack.redo()
    assert stored_traces3d_parents(project_path) == after  # the same ids again


def traces_after_holding(qtbot, session, handles, hold):
    """Once the worker has a connection (`handles`) and waits for `hold`: release it 0.3 s later and read the
    3D traces on the GUI thread, which must wait for the worker."""
    qtbot.waitUntil(lambda: bool(handles), timeout=10_000)
    threading.Timer(0.3, hold.set).start()
    t0 = time.perf_counter()
    traces = session.traces3d()
    assert time.perf_counter() - t0 > 0.2  # it waited for the worker
    return traces


def test_reads_and_edits_wait_for_the_edit_being_stored(session, project_path, qtbot, monkeypatch):
    """A read of the traces while the worker stores gets them as stored, and the next edit goes after it."""
    hold = threading.Event()
    writers = watch_writers(monkeypatch, hold)
    command, old = re_extraction(session)
    session.push_in_background(command)
    traces = traces_after_holding(qtbot, session, writers, hold)  # the worker has taken the write
    assert not {t.id for t in old} & {t.id for t in traces}
    assert [t.id for t in traces[-2:]] == [t.id for t in command.added]
    session.push(commands.EditTraces3D.setting(session, traces[-1:], "Set 1", set_id=1))
    assert [session.undo_stack.text(i) for i in range(2)] == ["Extract 2 3D traces", "Set 1"]
    assert set(stored_traces3d_parents(project_path)) == {t.id for t in session.traces3d()}
    session.undo_stack.undo()
    session.undo_stack.undo()
    assert {t.id for t in old} <= set(stored_traces3d_parents(project_path))


def test_a_failing_background_edit_is_reported_and_stores_nothing(session, project_path, qtbot):
    before = stored_traces2d(project_path)
    bad = commands.AddTraces2D(session, [Trace2D(0, "photo_01", LINE), Trace2D(0, "no such photo", LINE)])
    with qtbot.waitSignal(session.failed, timeout=10_000) as failed:
        session.push_in_background(bad)
    assert failed.args[0].startswith("Draw trace: ") and "FOREIGN KEY" in failed.args[0]
    assert stored_traces2d(project_path).keys() == before.keys()
    assert session.undo_stack.count() == 0 and len(session.traces2d("photo_01")) == len(
        [i for i, (image, *_) in before.items() if image == "photo_01"])


def test_closing_keeps_the_edit_being_stored(session, project_path, monkeypatch):
    hold = threading.Event()
    watch_writers(monkeypatch, hold)
    command, old = re_extraction(session)
    session.push_in_background(command)
    threading.Timer(0.2, hold.set).start()
    session.close()
    reopened = Session()
    reopened.open(project_path)
    try:
        ids = {t.id for t in reopened.traces3d()}
        assert not {t.id for t in old} & ids and {t.id for t in command.added} <= ids
    finally:
        reopened.close()


def test_after_opening_what_is_alive_leaves_the_full_collections(session, project_path, qtbot, monkeypatch):
    """A full garbage collection over everything the windows and the project hold took 0.1–0.3 s with the
    GIL, on whichever thread ran it: after opening, those objects are frozen out of it (and the 3D traces read
    in that same later pass)."""
    reads = []
    traces3d = Project.traces3d
    monkeypatch.setattr(Project, "traces3d",  # this project's reads: a worker of an earlier test may still read
                        lambda project: (Path(project.path) == project_path and reads.append(1)) or traces3d(project))
    gc.unfreeze()
    session.open(project_path)
    assert gc.get_freeze_count() == 0 and not reads  # not in the pass in which the windows reload
    qtbot.waitUntil(lambda: gc.get_freeze_count() > 10_000, timeout=5_000)
    assert reads == [1] and session.traces3d()  # read once, before freezing


def test_after_opening_the_3d_traces_are_read_by_a_worker(session, project_path, qtbot, monkeypatch):
    """Reading the 3D traces took the GUI thread 0.1–0.4 s on a loaded machine (issue 5). A window needing
    them while the worker reads waits for that read instead of reading again."""
    readers = []
    traces3d = Project.traces3d
    monkeypatch.setattr(Project, "traces3d", lambda project: readers.append(threading.current_thread())
                        or traces3d(project))
    hold = threading.Event()
    handles = watch_writers(monkeypatch, hold)  # the worker's connection waits for `hold`
    session.close()
    session.open(project_path)
    traces = traces_after_holding(qtbot, session, handles, hold)  # the worker has taken the read
    assert len(readers) == 1 and readers[0] is not threading.main_thread()
    assert [t.id for t in traces] == sorted(stored_traces3d_parents(project_path))
    qtbot.waitUntil(lambda: not session.jobs.running, timeout=10_000)
    assert session.traces3d() is traces and len(readers) == 1

    session.close()  # untouched, the worker's read fills the cache by itself
    session.open(project_path)
    qtbot.waitUntil(lambda: len(readers) == 2 and not session.jobs.running, timeout=10_000)
    assert readers[1] is not threading.main_thread()
    assert [t.id for t in session.traces3d()] == [t.id for t in traces] and len(readers) == 2
