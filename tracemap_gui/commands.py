"""Undoable edits of a project: each redo and each undo is one project transaction.

Push them with `Session.push`, which applies the edit first so that an error reaches the caller (and nothing
is pushed), then puts it on the undo stack. Traces a command adds get their ids on the first application
and keep them through undo and redo (`Project.restore_traces*`), so later commands that name them by id
stay valid.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from PySide6.QtCore import QTimer
from PySide6.QtGui import QUndoCommand

from engine.merge import relabel_components
from engine.project import Project
from engine.traces import Trace2D, Trace3D, kind_edit
from tracemap_gui import polyline_edit
from tracemap_gui.error_dialog import describe
from tracemap_gui.undo_memory import payload_bytes, read_payload

if TYPE_CHECKING:
    from sqlite3 import Connection

    from tracemap_gui.session import Session

_ABSENT = object()  # a result not stored
# the fields an analysis run (Orient, Analyse) sets on 3D traces; their vertices it leaves alone
ANALYSIS_FIELDS = ("normal", "method", "K", "M", "dispersion", "set_id", "term_start", "term_end", "component",
                   "extra")


class Change(NamedTuple):
    """What one step of a command did to the 2D or the 3D traces."""

    dimension: int  # 2 or 3
    removed: list
    stored: list  # added or changed, with their ids


class ProjectCommand(QUndoCommand):
    """One edit: subclasses write `_do` and `_undo`, each given the project and the open transaction and
    returning the `Change`s it made, so the session can update its caches without reading everything again."""

    dimension: int  # which traces the command edits: 2 or 3
    payload_fields: tuple[str, ...] = ()  # the attributes holding traces, which may wait on disk (UndoMemory)

    def __init__(self, session: Session, text: str):
        super().__init__(text)
        self._session = session
        self._skip_redo = self._skip_undo = False
        self.stowed: Path | None = None  # the file holding the payload, once written
        self.released = False  # the payload is on disk only
        self._bytes: int | None = None

    def payload(self) -> dict[str, object]:
        return {name: getattr(self, name) for name in self.payload_fields}

    def payload_bytes(self) -> int:
        if self._bytes is None:  # once: after the first application the payload does not change
            self._bytes = payload_bytes(self.payload())
        return self._bytes

    def release(self) -> None:
        """Let go of the payload, which `stowed` holds."""
        for name in self.payload_fields:
            setattr(self, name, None)
        self.released = True

    def recall(self) -> None:
        """Read the payload back from `stowed` if it was released."""
        if self.released:
            self.adopt(read_payload(self.stowed))

    def adopt(self, payload: dict[str, object]) -> None:
        """Take the payload back (read from `stowed`)."""
        for name in self.payload_fields:
            setattr(self, name, payload[name])
        self.released = False

    def apply(self) -> None:
        """The first application; errors propagate. `QUndoStack.push` then calls `redo`, which skips once."""
        self._store(self._do)
        self._skip_redo = True

    def write(self, project: Project) -> list[Change]:
        """The first application's transaction alone, on a worker thread's handle on the project
        (`Session.push_in_background`: no Qt here); `applied` then tells the session what changed. Commands
        that do more after storing (an overridden `_store`) are applied with `apply`."""
        with project.transaction() as db:
            return self._do(project, db)

    def applied(self, changes: list[Change]) -> None:
        self._tell(changes)
        self._skip_redo = True

    def redo(self) -> None:
        if self._skip_redo:
            self._skip_redo = False
            return
        if not self._guarded(self._do):  # the project is as before: so is the stack (QUndoStack moves on)
            self._skip_undo = True
            self._put_back(self._session.undo_stack.index())

    def undo(self) -> None:
        if self._skip_undo:
            self._skip_undo = False
            return
        if not self._guarded(self._undo):
            self._skip_redo = True
            self._put_back(self._session.undo_stack.index())

    def _put_back(self, index: int) -> None:
        """Return the stack to `index` (where it stands while this step runs: QUndoStack moves it after),
        once this step has returned; the step it then takes again is skipped, having changed nothing."""
        stack = self._session.undo_stack
        QTimer.singleShot(0, stack, lambda: stack.setIndex(index))

    def _do(self, project: Project, db: Connection) -> list[Change]:
        raise NotImplementedError

    def _undo(self, project: Project, db: Connection) -> list[Change]:
        raise NotImplementedError

    def _store(self, step: Callable[[Project, Connection], list[Change]]) -> None:
        project = self._session.project
        with project.transaction() as db:
            changes = step(project, db)
        self._tell(changes)

    def _tell(self, changes: list[Change]) -> None:
        for change in changes:
            if change.removed or change.stored:
                self._session.stored(*change)

    def _guarded(self, step: Callable[[Project, Connection], list[Change]]) -> bool:
        # Called by QUndoStack from C++, where an exception could not reach anyone: report it instead.
        try:
            self.recall()
            self._store(step)
        except Exception as exc:  # noqa: BLE001 - any failure is reported, the transaction rolled back
            self._session.failed.emit(f"{self.text()}: {describe(exc)}")
            return False
        return True


class _Methods(NamedTuple):
    add: Callable
    remove: Callable
    restore: Callable
    update: Callable


def _methods(project: Project, dimension: int) -> _Methods:
    """The project's methods for 2D or 3D traces. 2D traces keep the components they are given: undo restores
    them as they were, and the trace layer labels a photo's traces itself."""
    if dimension == 2:
        return _Methods(partial(project.add_traces2d, relabel=False), project.remove_traces2d,
                        project.restore_traces2d, project.update_traces2d)
    return _Methods(project.add_traces3d, project.remove_traces3d, project.restore_traces3d,
                    project.update_traces3d)


class _Replace(ProjectCommand):
    """Remove some traces and add others as one edit."""

    payload_fields = ("removed", "added")

    def __init__(self, session: Session, removed: Iterable, added: Iterable, text: str):
        super().__init__(session, text)
        self.removed = list(removed)
        self.added = list(added)
        self._have_ids = False

    def _do(self, project: Project, db: Connection) -> list[Change]:
        methods = _methods(project, self.dimension)
        methods.remove([t.id for t in self.removed], db)
        if self._have_ids:
            methods.restore(self.added, db)
        else:
            ids = methods.add(self.added, db)
            self.added = [replace(t, id=i) for t, i in zip(self.added, ids)]
            self._have_ids = True
        return [Change(self.dimension, self.removed, self.added)]

    def _undo(self, project: Project, db: Connection) -> list[Change]:
        methods = _methods(project, self.dimension)
        methods.remove([t.id for t in self.added], db)
        methods.restore(self.removed, db)
        return [Change(self.dimension, self.added, self.removed)]


class _Update(ProjectCommand):
    """Change traces in place (same ids): `before` and `after` hold the whole traces."""

    payload_fields = ("before", "after")

    def __init__(self, session: Session, before: Sequence, after: Sequence, text: str):
        super().__init__(session, text)
        self.before, self.after = list(before), list(after)

    def _do(self, project: Project, db: Connection) -> list[Change]:
        _methods(project, self.dimension).update(self.after, db)
        return [Change(self.dimension, [], self.after)]

    def _undo(self, project: Project, db: Connection) -> list[Change]:
        _methods(project, self.dimension).update(self.before, db)
        return [Change(self.dimension, [], self.before)]


# -- 2D traces -----------------------------------------------------------------------------------------

class ReplaceTraces2D(_Replace):
    """Remove some 2D traces and add others. The 3D traces made from removed ones go too (as `tracemap
    autotrace` does), so extracting the new ones later leaves no stale duplicate; undo brings them back."""

    dimension = 2
    payload_fields = ("removed", "added", "removed3d")

    def __init__(self, session: Session, removed: Iterable[Trace2D], added: Iterable[Trace2D], text: str):
        super().__init__(session, removed, added, text)
        parents = {t.id for t in self.removed}
        self.removed3d = [t for t in session.traces3d() if parents.intersection(t.parents)] if parents else []

    def _do(self, project: Project, db: Connection) -> list[Change]:
        project.remove_traces3d([t.id for t in self.removed3d], db)
        return [*super()._do(project, db), Change(3, self.removed3d, [])]

    def _undo(self, project: Project, db: Connection) -> list[Change]:
        changes = super()._undo(project, db)
        project.restore_traces3d(self.removed3d, db)
        return [*changes, Change(3, [], self.removed3d)]


class AddTraces2D(ReplaceTraces2D):
    def __init__(self, session: Session, traces: Iterable[Trace2D], text: str = "Draw trace"):
        super().__init__(session, [], traces, text)


class RemoveTraces2D(ReplaceTraces2D):
    def __init__(self, session: Session, traces: Iterable[Trace2D], text: str = "Erase traces"):
        super().__init__(session, traces, [], text)


class SplitTrace2D(ReplaceTraces2D):
    """Cut a trace in two at a point on its segment `segment` (fraction `t` along it)."""

    def __init__(self, session: Session, trace: Trace2D, segment: int, t: float):
        first, second = polyline_edit.split(trace.polyline, segment, t)
        pieces = [replace(trace, id=0, polyline=first), replace(trace, id=0, polyline=second)]
        super().__init__(session, [trace], pieces, "Split trace")


class JoinTraces2D(ReplaceTraces2D):
    """Join two traces of one photo at their nearest ends; hand-drawn if either was."""

    def __init__(self, session: Session, a: Trace2D, b: Trace2D):
        source = "auto" if a.source == b.source == "auto" else "manual"
        joined = replace(a, id=0, polyline=polyline_edit.join_nearest_ends(a.polyline, b.polyline),
                         source=source)
        super().__init__(session, [a, b], [joined], "Join traces")


class ReplaceAutoTraces(ReplaceTraces2D):
    """Accept auto-trace proposals on a photo: they replace the photo's earlier automatic traces.

    Traces edited by hand are 'manual' and survive a new auto-trace run.
    """

    def __init__(self, session: Session, image: str, proposals: Iterable[Trace2D]):
        old = [t for t in session.traces2d(image) if t.source == "auto"]
        new = [replace(t, id=0, image=image, source="auto") for t in proposals]
        super().__init__(session, old, new, f"Accept {len(new)} auto traces")


class EditTrace2D(_Update):
    """New vertices for one trace (moved, inserted or deleted by hand): it becomes a manual trace."""

    dimension = 2

    def __init__(self, session: Session, trace: Trace2D, polyline: np.ndarray, text: str = "Edit vertices"):
        super().__init__(session, [trace], [replace(trace, polyline=polyline, source="manual")], text)


# -- 3D traces (the 3D viewer's edits, and extraction) ----------------------------------------------------

class EditTraces3D(_Update):
    """Field changes of 3D traces (termination, orientation, set, ...), ids unchanged."""

    dimension = 3

    @classmethod
    def setting(cls, session: Session, traces: Iterable[Trace3D], text: str, **fields: object) -> EditTraces3D:
        """The same field values on every trace, e.g. `EditTraces3D.setting(s, ts, "Set 2", set_id=2)`."""
        traces = list(traces)
        return cls(session, traces, [replace(t, **fields) for t in traces], text)


class TrimTrace3D(EditTraces3D):
    """A trace cut to part of itself (`engine.merge.trim`), with the connected components relabelled over the
    result as after a merge (the part cut off may have been its only contact with another trace); the traces
    whose component changes are updated in the same transaction, so undo restores every label."""

    def __init__(self, session: Session, trace: Trace3D, trimmed: Trace3D, tolerance: float,
                 text: str = "Trim trace"):
        rest = [t for t in session.traces3d() if t.id != trace.id]
        labelled = relabel_components([*rest, trimmed], tolerance)
        moved = [(old, new) for old, new in zip(rest, labelled) if new.component != old.component]
        super().__init__(session, [trace, *(old for old, _ in moved)], [labelled[-1], *(new for _, new in moved)],
                         text)


class ReplaceTraces3D(_Replace):
    """Remove some 3D traces and add others: a merge (many → one), or an extraction replacing old results."""

    dimension = 3


class MergeTraces3D(ReplaceTraces3D):
    """Replace traces by their merge (`engine.merge.merge_pair`) and relabel the connected components over the
    result, as `engine.merge.auto_merge` does: the other traces whose component changes are updated in the same
    transaction, so undo restores every label."""

    payload_fields = ("removed", "added", "before", "after")

    def __init__(self, session: Session, sources: Iterable[Trace3D], merged: Trace3D, tolerance: float,
                 text: str = "Merge traces"):
        super().__init__(session, sources, [merged], text)
        gone = {t.id for t in self.removed}
        rest = [t for t in session.traces3d() if t.id not in gone]
        labelled = relabel_components([*rest, merged], tolerance)
        self.added = labelled[-1:]
        moved = [(old, new) for old, new in zip(rest, labelled) if new.component != old.component]
        self.before, self.after = [old for old, _ in moved], [new for _, new in moved]

    def _do(self, project: Project, db: Connection) -> list[Change]:
        (change,) = super()._do(project, db)
        project.update_traces3d(self.after, db)
        return [Change(3, change.removed, [*change.stored, *self.after])]

    def _undo(self, project: Project, db: Connection) -> list[Change]:
        (change,) = super()._undo(project, db)
        project.update_traces3d(self.before, db)
        return [Change(3, change.removed, [*change.stored, *self.before])]


class SetKind(ProjectCommand):
    """Make traces of one kind (`engine.traces.kind_edit`): the 2D and 3D traces named, and every trace
    linked to them by extraction, as one edit. `changed` says whether any trace changes."""

    dimension = 3  # both, stored on the GUI thread (`Session.push`)
    payload_fields = ("before2d", "after2d", "before3d", "after3d")

    def __init__(self, session: Session, kind: str, *, ids2d: Iterable[int] = (), ids3d: Iterable[int] = ()):
        traces2d = [t for image in session.images() for t in session.traces2d(image)]
        traces3d = session.traces3d()
        self.after2d, self.after3d = kind_edit(kind, traces2d, traces3d, ids2d=ids2d, ids3d=ids3d)
        old2d, old3d = {t.id: t for t in traces2d}, {t.id: t for t in traces3d}
        self.before2d = [old2d[t.id] for t in self.after2d]
        self.before3d = [old3d[t.id] for t in self.after3d]
        n = len(self.after2d) + len(self.after3d)
        super().__init__(session, f"Make {n} trace{'' if n == 1 else 's'} {kind}")

    @property
    def changed(self) -> bool:
        return bool(self.after2d or self.after3d)

    def _do(self, project: Project, db: Connection) -> list[Change]:
        return self._write(project, db, self.after2d, self.after3d)

    def _undo(self, project: Project, db: Connection) -> list[Change]:
        return self._write(project, db, self.before2d, self.before3d)

    @staticmethod
    def _write(project: Project, db: Connection, traces2d: list[Trace2D], traces3d: list[Trace3D]) -> list[Change]:
        project.update_traces2d(traces2d, db)
        project.update_traces3d(traces3d, db)
        return [Change(2, [], traces2d), Change(3, [], traces3d)]


class StoreAnalysis3D(ProjectCommand):
    """What an analysis run (Orient, Analyse) found, stored as one edit: the fields it changed on 3D traces (ids
    unchanged), its project results (`results`: name → value) and their entries of the "basis" result, which
    say which traces they were computed on (`Project.record_basis`), so the out-of-date warnings go. Undo
    restores the traces, the results (one the run added is removed) and those basis entries; the entries of
    other results (maps computed meanwhile) are left as they are."""

    dimension = 3
    payload_fields = ("before", "after", "_traces")  # the results are small, and `_previous` marks with _ABSENT

    def __init__(self, session: Session, traces: Iterable[Trace3D], results: dict[str, object], text: str):
        super().__init__(session, text)
        old = {t.id: t for t in session.traces3d()}
        pairs = [(old[t.id], t) for t in traces if _differs(old[t.id], t)]
        self.before, self.after = [b for b, _ in pairs], [a for _, a in pairs]
        self.results = dict(results)
        project = session.project
        self._previous = {name: project.result(name, _ABSENT) for name in self.results}
        basis = project.result("basis", _ABSENT)
        self._had_basis = basis is not _ABSENT
        self._previous_basis = {n: basis[n] for n in self.results if self._had_basis and n in basis}
        changed = {t.id: t for t in self.after}
        self._traces = [changed.get(i, t) for i, t in old.items()]  # every trace once stored: the basis digests them

    def _do(self, project: Project, db: Connection) -> list[Change]:
        project.update_traces3d(self.after, db)
        for name, value in self.results.items():
            project.set_result(name, value, db)
        project.record_basis(list(self.results), self._traces, db)
        return [Change(3, [], self.after)]

    def _undo(self, project: Project, db: Connection) -> list[Change]:
        project.update_traces3d(self.before, db)
        for name, value in self._previous.items():
            if value is _ABSENT:
                project.remove_result(name, db)
            else:
                project.set_result(name, value, db)
        basis = project.result("basis", {})
        for name in self.results:  # in place: the entries keep their order, so the stored text is as it was
            if name in self._previous_basis:
                basis[name] = self._previous_basis[name]
            else:
                basis.pop(name, None)
        if basis or self._had_basis:
            project.set_result("basis", basis, db)
        else:
            project.remove_result("basis", db)
        return [Change(3, [], self.before)]

    def _tell(self, changes: list[Change]) -> None:
        # the results changed even where no trace did: the views showing them (the plots) refresh all the same
        for change in changes:
            self._session.stored(*change)


def _differs(a: Trace3D, b: Trace3D) -> bool:
    return any(_comparable(getattr(a, f)) != _comparable(getattr(b, f)) for f in ANALYSIS_FIELDS)


def _comparable(value: object) -> str:
    """A field's value as `engine.traces.traces_digest` sees it: NaN equals NaN, an array its values."""
    return repr(None if value is None else np.asarray(value).tolist())


class Storage(NamedTuple):
    """How the project stores one kind of item with an id (facets, scanlines): unbound `Project` methods
    add(item, db) → new id, remove(id, db) and restore(item, db) (re-insert under its own id)."""

    add: Callable
    remove: Callable
    restore: Callable


FACETS = Storage(Project.add_facet, Project.remove_facet, Project.restore_facet)
SCANLINES = Storage(Project.add_scanline, Project.remove_scanline, Project.restore_scanline)
SCAN_CIRCLES = Storage(Project.add_scan_circle, Project.remove_scan_circle, Project.restore_scan_circle)


class EditItems(ProjectCommand):
    """Remove some stored items and add others as one edit; `changed` runs after every do and undo so a tool
    shows what the project holds. Added items keep the ids of their first storing through undo and redo."""

    def __init__(self, session: Session, storage: Storage, removed: Sequence, added: Sequence, text: str,
                 changed: Callable[[], None]):
        super().__init__(session, text)
        self.storage, self.removed, self.added = storage, list(removed), list(added)
        self._changed = changed
        self._have_ids = False

    def _do(self, project: Project, db: Connection) -> list:
        for item in self.removed:
            self.storage.remove(project, item.id, db)
        if self._have_ids:
            for item in self.added:
                self.storage.restore(project, item, db)
        else:
            self.added = [replace(item, id=self.storage.add(project, item, db)) for item in self.added]
            self._have_ids = True
        return []

    def _undo(self, project: Project, db: Connection) -> list:
        for item in self.added:
            self.storage.remove(project, item.id, db)
        for item in self.removed:
            self.storage.restore(project, item, db)
        return []

    def _store(self, step: Callable[[Project, Connection], list]) -> None:
        super()._store(step)
        self._changed()
