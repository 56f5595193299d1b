"""The 3D viewer's merge and trim tools: merge two selected traces, step through automatic merge
suggestions, trim a trace to the part between two clicked vertices (engine.merge; MATHS §5).

Nothing is stored unseen: each proposal is drawn over the scene (the result as a bright line, the traces it
replaces dimmed) with Accept (Enter) / Cancel (Esc) in a dock, and accepting pushes one undoable command.
Suggestions are computed in the background. When an earlier accept consumed a trace of a later suggestion,
the suggestion is re-resolved to the merged trace and must pass the duplicate rules again, so a chain of
suggestions cannot join two fractures through an ambiguous link (as in `engine.merge.auto_merge`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import pyvista as pv
from PySide6.QtCore import QObject, Qt
from PySide6.QtGui import QAction, QKeySequence
from PySide6.QtWidgets import (QDockWidget, QFormLayout, QGridLayout, QLabel, QListWidget, QToolBar, QToolButton,
                               QVBoxLayout, QWidget)
from vtkmodules.util.numpy_support import vtk_to_numpy

from engine.cameras import Camera
from engine.errors import TracemapError
from engine.merge import (FOR_REVIEW, Joint, MergeSuggestion, Overlap, joint, merge_pair, overlap, suggest_merges,
                          trim)
from engine.mesh import Mesh
from engine.register import length_scale
from engine.sight import Sight
from engine.traces import Trace3D
from tracemap_gui.commands import MergeTraces3D, TrimTrace3D
from tracemap_gui.error_dialog import describe, show_error
from tracemap_gui.length_box import length_box
from tracemap_gui.mesh_tracer import MeshTracer, survey
from tracemap_gui.scene_view import nearest_point
from tracemap_gui.workers import Task

if TYPE_CHECKING:
    from tracemap_gui.viewer3d import Viewer3D

DEFAULT_TOLERANCE = 0.03  # m: the default of `tracemap merge --tolerance`, 2–3 × the ray-casting error
TOLERANCE_SETTING = "merge/tolerance"
PREVIEW_ACTOR, MARKS_ACTOR = "merge-preview", "merge-marks"
PREVIEW_COLOR = (0, 200, 255)  # neither a palette colour nor the selection's magenta
MARK_COLOR = (255, 215, 0)
DIM_COLOR = (150, 150, 150)  # darker than unassigned traces (235), lighter than termination-mode lines (40)
PREVIEW_WIDTH = 2.0  # × the traces' line width, so the preview shows around the trace it replaces
VERTEX_PICK_PX = 12  # how near (display pixels) a trim click must fall to a vertex of the trace
FRAME_MARGIN = 0.5  # framing a suggestion: the pair's bounding box grows by this share of its size
ON_TOP = -66000  # VTK coincident-topology offset units: the preview is drawn in front of the trace it covers


@dataclass(frozen=True)
class Proposal:
    """An edit on show: the traces it replaces, what replaces them, and a sentence saying what it does."""

    sources: tuple[Trace3D, ...]
    result: Trace3D
    text: str

    @property
    def is_merge(self) -> bool:
        """Two traces become one (a trim changes one trace in place)."""
        return len(self.sources) == 2


@dataclass
class Suggested:
    """One merge suggestion, what the list shows of it (the overlap of duplicates, the joint of pieces end
    to end), and what the user made of it."""

    suggestion: MergeSuggestion
    measure: Overlap | Joint
    status: str = ""  # "" while pending, "accepted" or "skipped"

    def label(self, scale: float = 1.0) -> str:
        """What the list shows; distances times `scale` (the registration's, so they read as exports do)."""
        s, m = self.suggestion, self.measure
        mark = {"": "", "accepted": "✓ ", "skipped": "✗ "}[self.status]
        if s.kind == "candidate":  # the rules left these apart: the list says so before the user reads why
            return f"{mark}? {s.a_id} + {s.b_id}: maybe, across a {scale * m.gap * 1000:.0f} mm hidden gap (your call)"
        if s.kind == "kinds":
            return f"{mark}? {s.a_id} + {s.b_id}: one trace of two kinds (give them one kind to merge)"
        if isinstance(m, Joint):
            return (f"{mark}{s.a_id} + {s.b_id}: end to end, {scale * m.gap * 1000:.0f} mm gap, "
                    f"{m.angle:.1f}° off straight")
        along = (f"overlap end to end for {scale * m.overlap_length * 500:.0f} mm" if m.end_to_end
                 else f"{max(m.fraction_ab, m.fraction_ba):.0%} overlap")
        direction = "" if np.isnan(m.angle) else f", {m.angle:.1f}°"  # NaN: a shred, too short for a direction
        return f"{mark}{s.a_id} + {s.b_id}: {along}, {scale * m.separation * 1000:.1f} mm apart{direction}"


def find_suggestions(traces: list[Trace3D], *, tolerance: float, mesh: Mesh | None, cameras: dict[str, Camera],
                     known: Sight | None, tracers: MeshTracer,
                     progress: Callable[[float, str], None]) -> tuple[list[Suggested], Sight | None]:
    """`suggest_merges` with each pair's overlap or joint, best first (runs in a `workers.Task`), and the
    survey used. With the mesh, pieces cut by an occlusion in every photo are suggested too (engine.merge
    rules H1–H5), and after every suggestion the rules are sure of, the pieces that may continue each other
    across such a gap but that the rules leave apart (kind "candidate"), for the user to judge, and last
    the duplicates of two kinds (kind "kinds"), which merge once given one kind."""
    sight = survey(mesh, cameras, known, tracers, progress)
    progress(0.1, "comparing traces")
    found = suggest_merges(traces, tolerance=tolerance, sight=sight, review=True)
    progress(0.9, "measuring overlaps and joints")
    by_id = {t.id: t for t in traces}
    measure = {"overlap": overlap, "bridge": joint, "candidate": joint, "kinds": overlap}
    return [Suggested(s, measure[s.kind](by_id[s.a_id], by_id[s.b_id], tolerance=tolerance)) for s in found], sight


def merge_proposal(a: Trace3D, b: Trace3D, tolerance: float, sight: Sight | None = None,
                   scale: float = 1.0) -> Proposal:
    """The merge of a and b as a proposal (a gap told times `scale`, the registration's); a TracemapError says
    why they cannot be merged."""
    merged = merge_pair(a, b, tolerance=tolerance, sight=sight)
    ov = overlap(a, b, tolerance=tolerance)
    if ov.overlaps:
        how = f"{max(ov.fraction_ab, ov.fraction_ba):.0%} overlap"
    else:  # merge_pair bridges any gap: say how wide, so a wrong pair shows before it is accepted
        gap = min(np.linalg.norm(p - q) for p in a.points[[0, -1]] for q in b.points[[0, -1]])
        how = f"no overlap, a {scale * gap * 1000:.0f} mm gap bridged by a spline"
    return Proposal((a, b), merged, f"Merge traces {a.id} and {b.id} ({how}): {len(merged.points)} vertices")


def trim_proposal(trace: Trace3D, start: int, stop: int) -> Proposal:
    """Vertices [start, stop) of `trace` as a proposal; a TracemapError when fewer than 2 remain."""
    trimmed = trim(trace, start, stop)
    return Proposal((trace,), trimmed, f"Trim trace {trace.id} to vertices {start}–{stop - 1} "
                                       f"({len(trimmed.points)} of {len(trace.points)})")


class MergePanel(QWidget):
    """The dock's contents: what is on show, the suggestions, the merge tolerance and the tool's buttons."""

    def __init__(self, tool: MergeTool):
        super().__init__()
        self.message = QLabel(self)
        self.message.setObjectName("merge-message")
        self.message.setWordWrap(True)
        self.list = QListWidget(self)
        self.list.setObjectName("merge-suggestions")
        self.list.currentRowChanged.connect(tool.go_to)
        self.tolerance = length_box(self, "merge-tolerance", "overlap distance, 2–3 × the ray-casting error "
                                    "(MATHS §5)", low=0.1, high=10_000.0, decimals=1, unit="mm")
        self.scale = 1.0  # the registration's: distances read and typed in its frame
        self.buttons: dict[QAction, QToolButton] = {}
        grid = QGridLayout()
        rows = [(tool.previous_action, tool.next_action), (tool.skip_action, tool.accept_all_action),
                (tool.keep_start_action, tool.keep_end_action), (tool.accept_action, tool.cancel_action)]
        for r, row in enumerate(rows):
            for c, action in enumerate(row):
                button = QToolButton(self)
                button.setDefaultAction(action)
                button.setToolButtonStyle(Qt.ToolButtonStyle.ToolButtonTextOnly)
                self.buttons[action] = button
                grid.addWidget(button, r, c)
        self.form = QFormLayout()
        self.form.addRow("Tolerance", self.tolerance)
        layout = QVBoxLayout(self)
        layout.addWidget(self.message)
        layout.addWidget(self.list)
        layout.addLayout(self.form)
        layout.addLayout(grid)

    def show_suggestions(self, items: list[Suggested]) -> None:
        self.list.blockSignals(True)
        self.list.clear()
        self.list.addItems([item.label(self.scale) for item in items])
        self.list.blockSignals(False)

    def set_row(self, row: int, item: Suggested | None = None) -> None:
        """Make `row` current (without asking the tool to go there), relabelling it from `item`."""
        self.list.blockSignals(True)
        if item is not None:
            self.list.item(row).setText(item.label(self.scale))
        self.list.setCurrentRow(row)
        self.list.blockSignals(False)


class MergeTool(QObject):
    """Merge, suggestion and trim modes of one 3D viewer; at most one proposal is on show at a time."""

    def __init__(self, viewer: Viewer3D):
        super().__init__(viewer)
        self.viewer, self.session = viewer, viewer.session
        self.mode: str | None = None  # None, "pair", "suggest" or "trim"
        self.proposal: Proposal | None = None
        self.suggestions: list[Suggested] = []
        self.index = 0
        self.marks: list[int] = []  # trim: the clicked vertices
        self._sources: tuple[Trace3D, ...] = ()  # pair: the two traces; trim: the trace
        self._merged_into: dict[int, int] = {}  # suggestions: source id → the trace its accept made
        self._dimmed: tuple[object, np.ndarray, np.ndarray] | None = None  # actor, cells, their colours
        self._searching = False
        self._storing = False
        self._sight: Sight | None = None  # the survey of the last search, for the next (one per mesh)
        self._build_actions()
        self.panel = MergePanel(self)
        self.panel.tolerance.valueChanged.connect(self._tolerance_changed)
        self.dock = QDockWidget("Merge and trim", viewer)
        self.dock.setObjectName("merge-dock")
        self.dock.setFeatures(QDockWidget.DockWidgetFeature.DockWidgetMovable
                              | QDockWidget.DockWidgetFeature.DockWidgetFloatable)  # Cancel closes it
        self.dock.setWidget(self.panel)
        viewer.addDockWidget(Qt.DockWidgetArea.RightDockWidgetArea, self.dock)
        # connected after the viewer's own slots, so these run once it has redrawn the traces
        self.session.traces3d_changed.connect(self._traces_changed)
        self.session.selection_changed.connect(self._draw)
        self.session.opened.connect(self._load_tolerance)
        self.session.closed.connect(self.cancel)
        viewer.color_box.currentTextChanged.connect(self._draw)
        self._load_tolerance()
        self._update()

    def _build_actions(self) -> None:
        self.merge_action = self._action("Merge", "M", self.merge_selected)
        self.suggest_action = self._action("Suggest merges…", None, self.suggest)
        self.trim_action = self._action("Trim", "T", self.trim_selected)
        self.accept_action = self._action("Accept", [Qt.Key.Key_Return, Qt.Key.Key_Enter], self.accept)
        self.cancel_action = self._action("Cancel", Qt.Key.Key_Escape, self.cancel)
        self.next_action = self._action("Next", "N", lambda: self.step(1))
        self.previous_action = self._action("Previous", "B", lambda: self.step(-1))
        self.skip_action = self._action("Skip", None, self.skip)
        self.accept_all_action = self._action("Accept all remaining", None, self.accept_all)
        self.accept_all_action.setToolTip("accept every pending suggestion but the ones marked ?, which the "
                                          "rules leave to you")
        self.keep_start_action = self._action("Keep start side", None, lambda: self.keep_side("start"))
        self.keep_end_action = self._action("Keep end side", None, lambda: self.keep_side("end"))
        tools = [self.merge_action, self.suggest_action, self.trim_action]
        self.viewer.findChild(QToolBar, "viewer3d-toolbar").addActions(tools)
        menu = self.viewer.menuBar().addMenu("&Merge")
        menu.addActions(tools)
        menu.addSeparator()
        menu.addActions([self.accept_action, self.cancel_action, self.next_action, self.previous_action])

    def _action(self, text: str, keys, slot: Callable[[], None]) -> QAction:
        action = QAction(text, self.viewer)
        keys = [] if keys is None else keys if isinstance(keys, list) else [keys]
        action.setShortcuts([QKeySequence(k) for k in keys])
        action.triggered.connect(slot)
        self.viewer.addAction(action)  # window-wide shortcut, whichever child has the focus
        return action

    @property
    def tolerance(self) -> float:
        """The merge tolerance in metres of the mesh (typed in mm of the registered frame, if there is one)."""
        self.panel.scale = length_scale(self.session.similarity())
        return self.panel.tolerance.value() / 1000 / self.panel.scale

    # -- starting and ending --------------------------------------------------------------------------

    def merge_selected(self) -> None:
        """Preview the merge of the two selected traces."""
        traces = self.viewer.selected_traces()
        if len(traces) != 2:
            self._status(f"select two traces to merge (click one, Shift-click the other); {len(traces)} selected")
            return
        try:
            proposal = merge_proposal(*traces, self.tolerance, self._sight, self.panel.scale)
        except TracemapError as exc:
            show_error(self.viewer, f"Merging traces {traces[0].id} and {traces[1].id}", exc)
            return
        self.cancel()
        self.mode, self._sources = "pair", tuple(traces)
        self._propose(proposal, f"{proposal.text}. Accept (Enter) or Cancel (Esc).")

    def suggest(self) -> None:
        """Find merge suggestions in the background; the panel lists them when they arrive."""
        self.cancel()
        task = Task("Suggesting merges", find_suggestions, list(self.session.traces3d()),
                    tolerance=self.tolerance, mesh=self.viewer.mesh, cameras=self.session.cameras(),
                    known=self._sight, tracers=self.session.mesh_tracer)
        task.signals.done.connect(self._suggestions_found)
        task.signals.failed.connect(lambda exc: show_error(self.viewer, "Suggesting merges", exc))
        task.signals.ended.connect(self._search_ended)
        self._searching = True
        self._update()
        self.session.jobs.start(task)

    def trim_selected(self) -> None:
        """Start trimming the selected trace: the next clicks mark the vertices to keep between."""
        traces = self.viewer.selected_traces()
        if len(traces) != 1:
            self._status(f"select one trace to trim; {len(traces)} selected")
            return
        self.cancel()
        self.mode, self._sources = "trim", (traces[0],)
        self._propose(None, f"Trim trace {traces[0].id}: click two of its vertices to keep the part between "
                            "them, or one and keep a side.")

    def cancel(self) -> None:
        """Leave the current mode; nothing is stored."""
        self.mode, self.proposal, self._sources = None, None, ()
        self.marks, self.suggestions, self._merged_into = [], [], {}
        self._draw()
        self._update()

    # -- proposals ------------------------------------------------------------------------------------

    def accept(self) -> None:
        """Store the proposal on show as one undoable edit."""
        proposal = self.proposal
        if proposal is None:
            return
        stored = self._store(proposal)
        if stored is None:
            return
        if self.mode == "suggest":
            self._decide("accepted")
            self._merged_into.update({t.id: stored.id for t in proposal.sources})
            self._advance()
        else:
            self.cancel()
            self.session.select3d({stored.id})
            self._status(f"{proposal.text}: stored as trace {stored.id}")

    def _store(self, proposal: Proposal) -> Trace3D | None:
        """Push the command for a proposal; the stored trace, or None (the error is shown)."""
        if proposal.is_merge:
            command = MergeTraces3D(self.session, proposal.sources, proposal.result, self.tolerance,
                                    proposal.text)
        else:
            command = TrimTrace3D(self.session, proposal.sources[0], proposal.result, self.tolerance, proposal.text)
        self._storing = True
        try:
            self.session.push(command)
        except Exception as exc:  # noqa: BLE001 - shown to the user, nothing was stored
            show_error(self.viewer, proposal.text, exc)
            return None
        finally:
            self._storing = False
        return command.added[0] if proposal.is_merge else command.after[0]

    def _propose(self, proposal: Proposal | None, message: str) -> None:
        self.proposal = proposal
        self.panel.message.setText(message)
        self._draw()
        self._update()

    def _traces_changed(self) -> None:
        """Another edit (or undo) changed the traces: drop a proposal built on traces that changed."""
        if self._storing:
            return
        if self.mode == "suggest":
            self._show_suggestion()
            return
        current = {t.id: t for t in self.session.traces3d()}
        if any(current.get(t.id) is not t for t in self._sources):
            self.cancel()
            self._status("the traces changed: the merge or trim was cancelled")
        else:
            self._draw()

    def _tolerance_changed(self, mm: float) -> None:
        self.session.set_setting(TOLERANCE_SETTING, mm / 1000)
        if self.mode == "suggest":
            self._show_suggestion()
        elif self.mode == "pair":
            try:
                proposal = merge_proposal(*self._sources, self.tolerance, self._sight, self.panel.scale)
            except TracemapError as exc:
                self._propose(None, describe(exc))
                return
            self._propose(proposal, f"{proposal.text}. Accept (Enter) or Cancel (Esc).")

    def _load_tolerance(self) -> None:
        self.panel.tolerance.blockSignals(True)
        self.panel.tolerance.setValue(1000 * float(self.session.setting(TOLERANCE_SETTING, DEFAULT_TOLERANCE)))
        self.panel.tolerance.blockSignals(False)

    # -- suggestions ----------------------------------------------------------------------------------

    def _suggestions_found(self, found: tuple[list[Suggested], Sight | None]) -> None:
        items, self._sight = found
        if not items:
            self._status(f"no merge suggestions at a tolerance of {self.tolerance * 1000:g} mm")
            return
        self.cancel()
        self.mode, self.suggestions, self.index = "suggest", items, 0
        self.panel.show_suggestions(items)
        self._show_suggestion()

    def _search_ended(self) -> None:
        self._searching = False
        self._update()

    def go_to(self, index: int) -> None:
        """Show suggestion `index` (a row of the list)."""
        if self.mode == "suggest" and 0 <= index < len(self.suggestions):
            self.index = index
            self._show_suggestion()

    def step(self, delta: int) -> None:
        """The next (+1) or previous (−1) suggestion, wrapping round."""
        if self.mode == "suggest":
            self.go_to((self.index + delta) % len(self.suggestions))

    def skip(self) -> None:
        if self.mode == "suggest":
            self._decide("skipped")
            self._advance()

    def accept_all(self) -> None:
        """Accept every pending suggestion, from the current one round, as one undoable step; those whose
        traces no longer qualify are skipped, and candidates and duplicates of two kinds (`FOR_REVIEW`) stay
        pending: each needs the user's own judgement."""
        if self.mode != "suggest":
            return
        pending = [k for k in _rotated(len(self.suggestions), self.index)
                   if not self.suggestions[k].status and self.suggestions[k].suggestion.kind not in FOR_REVIEW]
        if not pending:
            self._status("only suggestions marked ? remain: accept or skip each one")
            return
        stack = self.session.undo_stack
        stack.beginMacro(f"Accept {len(pending)} merge suggestions")
        try:
            for k in pending:
                self.index = k
                proposal = self._suggestion_proposal(self.suggestions[k])
                stored = None if isinstance(proposal, str) else self._store(proposal)
                self._decide("skipped" if stored is None else "accepted")
                if stored is not None:
                    self._merged_into.update({t.id: stored.id for t in proposal.sources})
        finally:
            stack.endMacro()
        self._advance()

    def _show_suggestion(self) -> None:
        item = self.suggestions[self.index]
        self.panel.set_row(self.index)
        where = f"Suggestion {self.index + 1} of {len(self.suggestions)}"
        if item.status:
            self._propose(None, f"{where}: {item.status}.")
            return
        proposal = self._suggestion_proposal(item)
        pair = self._resolve(item.suggestion) if item.suggestion.kind == "kinds" else None
        if isinstance(proposal, str) and isinstance(pair, tuple):  # settled by a kind edit, which shows the merge
            self._frame(pair)
            self.session.select3d({t.id for t in pair})
            self._propose(None, f"{where}: {proposal}. Kind → Make selected traces gives the two selected one kind; "
                                "or skip it.")
            return
        if isinstance(proposal, str):
            self._propose(None, f"{where}: {proposal}. Skip it.")
            return
        self._frame(proposal.sources)
        self._propose(proposal, f"{where}: {proposal.text}. {item.suggestion.reason}.{self._rivals(item)}")

    def _rivals(self, item: Suggested) -> str:
        """For a candidate, the other pending candidates that share one of its traces: rivals are judged
        together (one piece continues in one trace at most)."""
        s = item.suggestion
        if s.kind != "candidate":
            return ""
        others = [x.suggestion for x in self.suggestions if x is not item and not x.status
                  and x.suggestion.kind == "candidate" and {x.suggestion.a_id, x.suggestion.b_id} & {s.a_id, s.b_id}]
        return (" Other candidates for these pieces: " + ", ".join(f"{o.a_id} + {o.b_id}" for o in others) + "."
                if others else "")

    def _suggestion_proposal(self, item: Suggested) -> Proposal | str:
        """The merge a suggestion stands for now, or why there is none."""
        pair = self._resolve(item.suggestion)
        if isinstance(pair, str):
            return pair
        try:
            return merge_proposal(*pair, self.tolerance, self._sight)
        except TracemapError as exc:
            return describe(exc)

    def _resolve(self, s: MergeSuggestion) -> tuple[Trace3D, Trace3D] | str:
        """The traces a suggestion names now: a trace an accepted suggestion consumed stands for the trace
        it became, and then the pair must pass the duplicate rules again (MATHS §5)."""
        by_id = {t.id: t for t in self.session.traces3d()}
        a, b = (self._current_id(i, by_id) for i in (s.a_id, s.b_id))
        if a is None or b is None:
            return f"trace {s.a_id if a is None else s.b_id} no longer exists"
        if a == b:
            return f"traces {s.a_id} and {s.b_id} are already merged (trace {a})"
        pair = by_id[a], by_id[b]
        if (a, b) != (s.a_id, s.b_id) and not suggest_merges(pair, tolerance=self.tolerance, sight=self._sight,
                                                             review=s.kind in FOR_REVIEW):
            return f"traces {s.a_id} and {s.b_id} are now traces {a} and {b}, which do not look like one fracture"
        return pair

    def _current_id(self, trace_id: int, by_id: dict[int, Trace3D]) -> int | None:
        while trace_id not in by_id and trace_id in self._merged_into:
            trace_id = self._merged_into[trace_id]
        return trace_id if trace_id in by_id else None

    def _decide(self, status: str) -> None:
        item = self.suggestions[self.index]
        item.status = status
        self.panel.set_row(self.index, item)

    def _advance(self) -> None:
        """Show the next pending suggestion, or end when every one is decided."""
        pending = [k for k in _rotated(len(self.suggestions), self.index) if not self.suggestions[k].status]
        if pending:
            self.go_to(pending[0])
            return
        accepted = sum(item.status == "accepted" for item in self.suggestions)
        self.cancel()
        self._status(f"merge suggestions done: {accepted} accepted")

    # -- trimming -------------------------------------------------------------------------------------

    def handle_click(self, x: int, y: int, additive: bool) -> bool:
        """While trimming, a click marks the vertex of the trace nearest it; True when it took the click."""
        if self.mode != "trim":
            return False
        trace = self._sources[0]
        k = nearest_point(self.viewer.view.plotter.renderer, trace.points, x, y, VERTEX_PICK_PX)
        if k is None:
            self._status(f"click on trace {trace.id} to mark a vertex")
            return True
        self.marks = [self.marks[0], k] if len(self.marks) == 1 else [k]
        if len(self.marks) == 2:
            lo, hi = sorted(self.marks)
            self._propose_trim(lo, hi + 1)
        else:
            self._propose(None, f"Vertex {k} of trace {trace.id} marked: click a second one, or keep a side.")
        return True

    def keep_side(self, side: str) -> None:
        """With one vertex marked, keep the trace from its start ("start") or to its end ("end")."""
        if self.mode != "trim" or len(self.marks) != 1:
            return
        k = self.marks[0]
        self._propose_trim(*((0, k + 1) if side == "start" else (k, len(self._sources[0].points))))

    def _propose_trim(self, start: int, stop: int) -> None:
        try:
            proposal = trim_proposal(self._sources[0], start, stop)
        except TracemapError as exc:
            self._propose(None, describe(exc))
            return
        self._propose(proposal, f"{proposal.text}. Accept (Enter) or Cancel (Esc).")

    # -- drawing --------------------------------------------------------------------------------------

    def _draw(self) -> None:
        """The proposal over the scene with its sources dimmed, and the marked vertices."""
        plotter = self.viewer.view.plotter
        shown = self._dimmed is not None or any(name in plotter.actors for name in (PREVIEW_ACTOR, MARKS_ACTOR))
        plotter.remove_actor([PREVIEW_ACTOR, MARKS_ACTOR], render=False)
        self._undim()
        if self.proposal is not None:
            line = pv.lines_from_points(self.proposal.result.points)
            width = PREVIEW_WIDTH * self.viewer.style.line_width
            actor = plotter.add_mesh(line, color=PREVIEW_COLOR, line_width=width, render_lines_as_tubes=True,
                                     lighting=False, pickable=False, name=PREVIEW_ACTOR)
            actor.GetMapper().SetRelativeCoincidentTopologyLineOffsetParameters(0, ON_TOP)
            self._dim({t.id for t in self.proposal.sources})
        if self.marks:
            actor = plotter.add_points(self._sources[0].points[self.marks], color=MARK_COLOR, point_size=16,
                                       render_points_as_spheres=True, pickable=False, name=MARKS_ACTOR)
            actor.GetMapper().SetRelativeCoincidentTopologyPointOffsetParameter(ON_TOP)
        if shown or self.proposal is not None or self.marks:  # rendering is slow offscreen: only on change
            self.viewer.view.refresh()

    def _dim(self, ids: set[int]) -> None:
        """Grey out the cells of these traces in the viewer's traces actor, keeping their colours to restore."""
        actor = self.viewer.view.plotter.actors.get("traces")
        if actor is None:
            return
        cells = actor.mapper.dataset.GetCellData()
        colours = vtk_to_numpy(cells.GetArray("rgb"))  # a view: writing it changes what VTK draws
        mask = np.isin(vtk_to_numpy(cells.GetArray("trace_id")), list(ids))
        self._dimmed = (actor, mask, colours[mask].copy())
        colours[mask] = DIM_COLOR
        cells.GetArray("rgb").Modified()

    def _undim(self) -> None:
        if self._dimmed is None:
            return
        actor, mask, before = self._dimmed
        self._dimmed = None
        if self.viewer.view.plotter.actors.get("traces") is actor:  # else the viewer drew it afresh
            cells = actor.mapper.dataset.GetCellData()
            vtk_to_numpy(cells.GetArray("rgb"))[mask] = before
            cells.GetArray("rgb").Modified()

    def _frame(self, traces: tuple[Trace3D, ...]) -> None:
        """Point the camera at the traces, keeping its direction, with a margin round them (drawn with the
        proposal next)."""
        points = np.vstack([t.points for t in traces])
        lo, hi = points.min(axis=0), points.max(axis=0)
        pad = FRAME_MARGIN * float((hi - lo).max())
        renderer = self.viewer.view.plotter.renderer
        renderer.ResetCamera(*np.column_stack([lo - pad, hi + pad]).ravel())
        renderer.ResetCameraClippingRange()  # over everything shown, not just the pair

    def _update(self) -> None:
        """Enable the actions and show the panel's parts that fit the mode."""
        suggesting, trimming = self.mode == "suggest", self.mode == "trim"
        self.accept_action.setEnabled(self.proposal is not None)
        self.cancel_action.setEnabled(self.mode is not None)
        for action in (self.next_action, self.previous_action, self.skip_action, self.accept_all_action):
            action.setEnabled(suggesting)
            self.panel.buttons[action].setVisible(suggesting)
        for action in (self.keep_start_action, self.keep_end_action):
            action.setEnabled(trimming and len(self.marks) == 1)
            self.panel.buttons[action].setVisible(trimming)
        self.panel.list.setVisible(suggesting)
        self.panel.form.setRowVisible(self.panel.tolerance, not trimming)
        self.suggest_action.setEnabled(not self._searching)
        self.dock.setVisible(self.mode is not None)

    def _status(self, message: str) -> None:
        self.viewer.statusBar().showMessage(message, 5000)


def _rotated(n: int, start: int) -> list[int]:
    """0 … n − 1 starting at `start` and wrapping round."""
    return [(start + k) % n for k in range(n)]
