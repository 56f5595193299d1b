"""A memory budget for the undo history: the traces of edits far from the current state wait on disk.

Every edit keeps the traces it replaced, so that undo can bring them back. A 3D trace vertex costs 52 bytes
(points and provenance), so at the paper's scale (about 400k trace pixels a photo) re-extracting 20 photos
keeps 0.8 GB in one command, and a long digitising session's history grew without limit (`QUndoStack`
limits only the number of commands, and only while it is empty). `UndoMemory` keeps in memory the traces of
the edits nearest the current state, up to `budget` bytes; the others' traces (their `payload_fields`) are
written, once, by a worker to a file in a private temporary folder, and an undo or redo reads them back
(`ProjectCommand.recall`). The history stays whole. The edit the next Undo takes stays in memory, and after
an undo the new next one is read back ahead, on a worker.
A write that fails (a full disk) leaves the traces in memory and says so once through `failed`; the files
go when their edits leave the stack and when the session closes.
"""

from __future__ import annotations

import os
import pickle
import tempfile
import weakref
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from PySide6.QtCore import QObject, QThreadPool, Signal
from PySide6.QtGui import QUndoStack
from shiboken6 import isValid

from engine.traces import Trace2D, Trace3D
from tracemap_gui.workers import Task

if TYPE_CHECKING:
    from tracemap_gui.commands import ProjectCommand

UNDO_MEMORY = 256 * 2**20
"""Default budget (bytes) of the traces the undo history keeps in memory."""

CLOSE_WAIT_MS = 60_000
"""On closing, how long to wait for a write in flight (a few seconds for a GB)."""

OBJECT_BYTES = 1000
"""What a trace costs beside its arrays (the instance, its dict, the array headers; measured ~900 B)."""


def payload_bytes(value: object) -> int:
    """Bytes of the traces and arrays in `value` (lists, tuples and dicts of them): an upper bound where
    traces are shared with the session's caches, whose current traces an edit's payload also names."""
    if isinstance(value, np.ndarray):
        return value.nbytes
    if isinstance(value, (Trace2D, Trace3D)):
        return OBJECT_BYTES + sum(v.nbytes for v in vars(value).values() if isinstance(v, np.ndarray))
    if isinstance(value, dict):
        return sum(payload_bytes(v) for v in value.values())
    if isinstance(value, (list, tuple)):
        return sum(payload_bytes(v) for v in value)
    return 0


def read_payload(path: Path) -> dict[str, object]:
    with open(path, "rb") as file:
        return pickle.load(file)  # our own file, in a folder only this user can read


def write_payload(path: Path, payload: dict[str, object], *, progress) -> Path:
    """Pickle `payload` to `path`, whole or not at all (a temporary name first)."""
    partial = path.with_suffix(".partial")
    try:
        with open(partial, "wb") as file:
            pickle.dump(payload, file, protocol=pickle.HIGHEST_PROTOCOL)
        os.replace(partial, path)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    return path


def _read_file(path: Path, *, progress) -> dict[str, object]:
    return read_payload(path)


class UndoMemory(QObject):
    """Keeps the traces the undo history holds in memory within `budget` bytes (module docstring)."""

    failed = Signal(str)  # the history could not be written to disk; it stays in memory

    def __init__(self, stack: QUndoStack, budget: int = UNDO_MEMORY):
        super().__init__(stack)
        self.budget = int(budget)
        self._stack = stack
        self._folder: tempfile.TemporaryDirectory | None = None
        self._writing: Path | None = None  # the file being written
        self._task: Task | None = None  # writing it: kept, or its signals would go before they arrive
        self._reading, self._read_task = False, None  # reading the next undo's payload ahead
        self._unreadable: set[Path] = set()  # files a read ahead failed on: not tried again
        self._broken = False  # a write failed: keep everything in memory from now on
        self._count = 0
        stack.indexChanged.connect(self.bound)

    def held(self) -> int:
        """Bytes of traces the history holds in memory now."""
        return sum(c.payload_bytes() for _, c in self._edits() if not c.released)

    def bound(self) -> None:
        """Release the traces of the edits farthest from the current state until the rest fit the budget,
        writing each to disk first (one at a time, on a worker; this runs again when a write ends)."""
        if not isValid(self._stack):  # a stack being deleted clears itself first, which moves its index
            return
        edits = self._edits()
        self._sweep([command for _, command in edits])
        index, total = self._stack.index(), 0
        # nearest first: the next undo (index - 1), the next redo (index), the one before, ...
        for i, command in sorted(edits, key=lambda e: 2 * (index - 1 - e[0]) if e[0] < index else 2 * (e[0] - index) + 1):
            if command.released or not command.payload_fields:
                continue
            size = command.payload_bytes()
            if i == index - 1 or total + size <= self.budget:
                total += size
            elif command.stowed is not None:
                command.release()
            elif self._writing is None and not self._broken:
                self._write(command)
        self._read_ahead([command for i, command in edits if i == index - 1 and command.released])

    def _read_ahead(self, released: list[ProjectCommand]) -> None:
        """Read back on a worker the next undo's payload (released while it was farther from the current
        state), so stepping back through the history does not wait for the disk."""
        released = [c for c in released if c.stowed not in self._unreadable]
        if not released or self._reading:
            return
        command, self._reading = released[0], True
        edit, path = weakref.ref(command), command.stowed
        task = self._read_task = Task("Reading the undo history", _read_file, path)
        task.signals.done.connect(lambda payload: self._adopt(edit, payload))
        task.signals.failed.connect(lambda exc: self._unreadable.add(path))  # the undo itself will say why
        task.signals.ended.connect(self._read_ended)
        QThreadPool.globalInstance().start(task.run)

    def _adopt(self, edit: weakref.ref, payload: dict[str, object]) -> None:
        command = edit()
        if command is not None and command.released:  # else recalled meanwhile by an undo, or gone
            command.adopt(payload)

    def _read_ended(self) -> None:
        self._reading, self._read_task = False, None
        self.bound()

    def close(self) -> None:
        """Delete the files (the stack is cleared first: its commands hold their names) and start afresh,
        once a write or read in flight has ended (it would leave a file behind, or signal a deleted object
        at exit); the session's own tasks were cancelled and waited for before."""
        if self._writing is not None or self._reading:
            QThreadPool.globalInstance().waitForDone(CLOSE_WAIT_MS)
        if self._folder is not None:
            self._folder.cleanup()
        self._folder, self._writing, self._task, self._broken = None, None, None, False
        self._reading, self._read_task = False, None

    def _edits(self) -> list[tuple[int, ProjectCommand]]:
        """The ProjectCommands on the stack with their index; those of a macro (Accept all) at its index."""
        edits = []
        for i in range(self._stack.count()):
            command = self._stack.command(i)
            parts = [command] if hasattr(command, "recall") else map(command.child, range(command.childCount()))
            # ProjectCommands are known by what they do: the module imports this one
            edits += [(i, part) for part in parts if hasattr(part, "recall")]
        return edits

    def _write(self, command: ProjectCommand) -> None:
        if self._folder is None:
            self._folder = tempfile.TemporaryDirectory(prefix="tracemap-undo-", ignore_cleanup_errors=True)
        folder, edit = self._folder, weakref.ref(command)
        self._count += 1
        path = self._writing = Path(folder.name) / f"{self._count}.pickle"
        task = self._task = Task("Keeping the undo history on disk", write_payload, path, command.payload())
        task.signals.done.connect(lambda written: self._written(edit, written))
        task.signals.failed.connect(lambda exc: self._write_failed(folder, exc))
        task.signals.ended.connect(lambda: self._write_ended(path))
        QThreadPool.globalInstance().start(task.run)

    def _written(self, edit: weakref.ref, path: Path) -> None:
        command = edit()
        if command is not None:
            command.stowed = path  # the sweep deletes it if the edit left the stack meanwhile

    def _write_failed(self, folder: tempfile.TemporaryDirectory, exc: BaseException) -> None:
        if folder is self._folder:  # not a write the closing of its project cut short
            self._broken = True
            self.failed.emit(f"Keeping the undo history on disk: {exc}. It stays in memory")

    def _write_ended(self, path: Path) -> None:
        if path == self._writing:
            self._writing = self._task = None
            self.bound()

    def _sweep(self, commands: list[ProjectCommand]) -> None:
        """Delete the files of edits no longer on the stack (undone and replaced by a new edit, or cleared)."""
        if self._folder is None:
            return
        kept = {c.stowed for c in commands if c.stowed is not None} | {self._writing}
        for path in Path(self._folder.name).glob("*.pickle"):
            if path not in kept:
                path.unlink(missing_ok=True)
