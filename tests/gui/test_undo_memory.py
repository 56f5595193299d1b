"""The undo history's memory budget (tracemap_gui/undo_memory.py): edits far from the current state keep
their traces on disk, and undo and redo still restore every state exactly."""

from __future__ import annotations

import gc
import time
import weakref
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PySide6.QtCore import QThreadPool

from tracemap_gui import commands, undo_memory


def _state(session) -> dict[int, bytes]:
    """The 3D traces as stored: id → their vertices."""
    return {t.id: t.points.tobytes() for t in session.project.traces3d()}


def _moved(session, text: str) -> commands.ReplaceTraces3D:
    """An edit the size of a re-extraction: every 3D trace replaced by a moved copy."""
    old = session.traces3d()
    new = [replace(t, id=0, points=t.points + 0.01) for t in old]
    return commands.ReplaceTraces3D(session, old, new, text)


def _settle(qtbot, session) -> None:
    """Wait for the history's writes (one at a time, each starting the next)."""
    qtbot.waitUntil(lambda: session.undo_memory._writing is None and QThreadPool.globalInstance().waitForDone(0),
                    timeout=20_000)


def _edits(session):
    return [c for _, c in session.undo_memory._edits()]


def test_the_history_stays_within_its_budget_and_undoes_every_state_exactly(session, qtbot):
    size = _moved(session, "probe").payload_bytes()
    session.undo_memory.budget = int(2.5 * size)  # room for two edits
    states, first_removed = [_state(session)], weakref.ref(session.traces3d()[0])
    for k in range(6):
        session.push(_moved(session, f"move {k}"))
        _settle(qtbot, session)
        states.append(_state(session))
        assert session.undo_memory.held() <= session.undo_memory.budget
    stack = session.undo_stack
    stack.beginMacro("two edits as one, as Accept all makes them")
    for k in range(2):
        session.push(_moved(session, f"macro {k}"))
    stack.endMacro()
    _settle(qtbot, session)
    states.append(_state(session))

    edits = _edits(session)
    # the macro is the next undo: both its edits stay, and fill the budget
    assert [c.released for c in edits] == [True] * 6 + [False] * 2
    assert all(Path(c.stowed).is_file() for c in edits[:6])
    gc.collect()
    assert first_removed() is None  # the traces the first edit replaced are no longer in memory

    for k in range(len(states) - 1, 0, -1):
        stack.undo()
        assert _state(session) == states[k - 1], k
        _settle(qtbot, session)
        assert session.undo_memory.held() <= session.undo_memory.budget + size
    for k in range(1, len(states)):
        stack.redo()
        assert _state(session) == states[k], k
        _settle(qtbot, session)
    assert [c.released for c in _edits(session)] == [True] * 6 + [False] * 2
    assert {c.text() for c in _edits(session) if c.released} == {f"move {k}" for k in range(6)}


def test_the_files_go_with_their_edits_and_with_the_session(session, qtbot):
    session.undo_memory.budget = 1  # only the next undo stays in memory
    for k in range(4):
        session.push(_moved(session, f"move {k}"))
        _settle(qtbot, session)
    folder = Path(_edits(session)[0].stowed).parent
    assert len(list(folder.glob("*.pickle"))) == 3
    for _ in range(3):
        session.undo_stack.undo()
    session.push(_moved(session, "a new branch"))  # the three undone edits leave the stack
    _settle(qtbot, session)
    assert [p.name for p in folder.glob("*.pickle")] == [Path(_edits(session)[0].stowed).name]
    session.close()
    assert not folder.exists()


def test_a_full_disk_keeps_the_history_in_memory_and_says_so(session, qtbot, monkeypatch):
    def full(path, payload, *, progress):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(undo_memory, "write_payload", full)
    session.undo_memory.budget = 1
    before = _state(session)
    with qtbot.waitSignal(session.failed, timeout=10_000) as failed:
        for k in range(3):
            session.push(_moved(session, f"move {k}"))
    _settle(qtbot, session)
    assert "No space left on device" in failed.args[0] and "stays in memory" in failed.args[0]
    assert not any(c.released for c in _edits(session))
    for _ in range(3):
        session.undo_stack.undo()
    assert _state(session) == before


def test_the_next_undo_is_read_back_ahead(session, qtbot):
    session.undo_memory.budget = 1
    for k in range(4):
        session.push(_moved(session, f"move {k}"))
        _settle(qtbot, session)
    assert [c.released for c in _edits(session)] == [True, True, True, False]
    session.undo_stack.undo()
    _settle(qtbot, session)
    assert [c.released for c in _edits(session)] == [True, True, False, True]  # the next undo, read back


def test_an_edit_whose_file_is_gone_is_reported_and_the_stack_stays_with_the_project(session, qtbot):
    session.undo_memory.budget = 1
    for k in range(3):
        session.push(_moved(session, f"move {k}"))
        _settle(qtbot, session)
    Path(_edits(session)[0].stowed).unlink()  # a cleaner of temporary files took it
    for _ in range(2):
        session.undo_stack.undo()
        _settle(qtbot, session)  # the read ahead of move 0 fails quietly
    now = _state(session)
    with qtbot.waitSignal(session.failed) as failed:
        session.undo_stack.undo()
    assert failed.args[0].startswith("move 0:") and _state(session) == now
    qtbot.waitUntil(lambda: session.undo_stack.index() == 1)  # put back: the project is still at 1
    session.undo_stack.redo()
    assert session.undo_stack.index() == 2 and _state(session) != now  # redo works on from there


def test_undoing_an_analysis_read_back_from_disk_removes_the_result_it_added(session, qtbot):
    """Its record of the results before marks one it added with a sentinel, which pickling would copy."""
    project = session.project
    project.remove_result("intensity")
    before, sets = _state(session), {t.id: t.set_id for t in project.traces3d()}
    analysed = [replace(t, set_id=t.set_id + 7) for t in session.traces3d()]
    session.push(commands.StoreAnalysis3D(session, analysed, {"intensity": {"value": 1}}, "Analyse"))
    session.undo_memory.budget = 1
    session.push(_moved(session, "later edit"))
    _settle(qtbot, session)
    assert _edits(session)[0].released
    session.undo_stack.undo()
    _settle(qtbot, session)
    session.undo_stack.undo()
    assert project.result("intensity") is None and {t.id: t.set_id for t in project.traces3d()} == sets
    assert _state(session) == before


def test_closing_while_a_write_runs_waits_for_it_and_leaves_no_file(session, qtbot, monkeypatch):
    def slow(path, payload, *, progress):
        time.sleep(0.5)
        return write(path, payload, progress=progress)

    write = undo_memory.write_payload
    monkeypatch.setattr(undo_memory, "write_payload", slow)
    session.undo_memory.budget = 1
    for k in range(2):
        session.push(_moved(session, f"move {k}"))
    folder = Path(session.undo_memory._writing).parent
    session.close()
    assert not folder.exists()


@pytest.mark.parametrize("value, expected", [
    (np.zeros(10), 80),
    ([np.zeros(3, np.int32), {"a": (np.zeros(2),)}], 28),
    ("text", 0),
])
def test_payload_bytes_counts_the_arrays(value, expected):
    assert undo_memory.payload_bytes(value) == expected
