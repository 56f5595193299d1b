"""How long the GUI thread freezes while long work runs, side by side with the same work run on the GUI thread.

Target (issue 5): long work runs in a background worker with a progress bar and cancel, and the window is
never frozen: no GUI-thread stall over 100 ms while work runs.

Run:  python tests/benchmarks/bench_gui_stall.py [--demo FOLDER] [WORD ...]
(offscreen; builds the demo in a temporary folder, or once in FOLDER and reuses it; only the jobs whose name
has one of the WORDs, e.g. `open`: the later jobs change the project, so a reused demo is meant for `open`)
The demo project (`engine.demo.run_demo`: a 20 m × 8 m wall of 512k faces, 5 photos of 1600 × 1200) is
opened in the image editor and the 3D viewer, and each job is started as the GUI starts it: opening the
project (the viewer reads the mesh, the editor the photo), "Extract all photos to 3D", "Auto-trace the
photo", and the intensity maps panel's Compute. A 10 ms QTimer heartbeat runs throughout; a stall is the
time between two heartbeats beyond those 10 ms, i.e. how long a click would have waited. A job is timed
from its start until no background work has run for SETTLE seconds (so the storing and redrawing of its
result on the GUI thread count too; the 3D view's frames are drawn on its own render thread, so only
handing the scene over to it is). While a heartbeat is late, a sampler thread notes where the GUI thread
is, so each stall is printed with the calls it was spent in (a stall with few samples is the GUI thread
waiting for the GIL, which the sampler needs too: some worker held it).
Peer: the same jobs with every `workers.Task` started through the session's `Jobs` run at once on the GUI
thread (what the window would do without workers): their stall is the whole job. (The photo view reads
photos on its own thread pool, the same on both sides.)
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import numpy as np  # noqa: E402
from PySide6.QtCore import QEventLoop, Qt, QTimer  # noqa: E402
from PySide6.QtWidgets import QApplication  # noqa: E402

import tracemap_gui  # noqa: E402,F401 - its PySide6 work-round must come first
from tracemap_gui import workers  # noqa: E402
from tracemap_gui.extraction import Extractor  # noqa: E402
from tracemap_gui.image_editor import ImageEditor  # noqa: E402
from tracemap_gui.session import Session  # noqa: E402
from tracemap_gui.viewer3d import Viewer3D  # noqa: E402

BEAT = 0.010  # s
SAMPLE = 0.020  # s between looks at the GUI thread while a heartbeat is late
LATE = 0.050  # s: a heartbeat this late is a stall worth explaining
SETTLE = 0.6  # s with no background work after a job: the plots panel starts its own 0.3 s after a change
TIMEOUT = 600.0  # s per job


class Heartbeat:
    """A precise 10 ms timer on the GUI thread, recording when each tick actually ran."""

    def __init__(self) -> None:
        self.beats: list[float] = []
        self._timer = QTimer(interval=round(BEAT * 1000))
        self._timer.setTimerType(Qt.TimerType.PreciseTimer)
        self._timer.timeout.connect(lambda: self.beats.append(time.perf_counter()))
        self._timer.start()


class StallSampler:
    """While the heartbeat is late, notes every SAMPLE s where the GUI thread is: which call stalls it."""

    def __init__(self, heart: Heartbeat) -> None:
        self.samples: list[str] = []
        self._heart, self._main = heart, threading.get_ident()
        threading.Thread(target=self._run, daemon=True).start()

    def _run(self) -> None:
        while True:
            time.sleep(SAMPLE)
            beats = self._heart.beats
            if beats and time.perf_counter() - beats[-1] > LATE:
                frame = sys._current_frames().get(self._main)
                if frame is not None:
                    self.samples.append(where(frame))

    def take(self) -> list[tuple[str, float]]:
        """The sampled calls since the last take, longest first, with their time (s)."""
        counts, self.samples = Counter(self.samples), []
        return [(call, n * SAMPLE) for call, n in counts.most_common(3)]


def where(frame) -> str:
    """'outer call → innermost call' of a stack: the outer one the innermost of tracemap's own (else the
    outermost below this benchmark, e.g. a paint event), as in 'viewer3d.py:_redraw → plotter.py:render'."""
    def name(f) -> str:
        return f"{Path(f.f_code.co_filename).name}:{f.f_code.co_name}"

    stack, inner = [], frame
    while frame is not None and "benchmarks" not in Path(frame.f_code.co_filename).parts:
        stack.append(frame)
        frame = frame.f_back
    if not stack:  # in the event loop itself: a C++ slot or paint with no Python below it
        return name(inner)
    ours = [f for f in stack if {"engine", "tracemap_gui"} & set(Path(f.f_code.co_filename).parts)]
    outer = ours[0] if ours else stack[-1]
    return name(outer) if outer is stack[0] else f"{name(outer)} → {name(stack[0])}"


class InlinePool:
    """Stands in for QThreadPool in the peer: runs each task at once, on the calling (GUI) thread."""

    @staticmethod
    def globalInstance() -> type[InlinePool]:
        return InlinePool

    @staticmethod
    def start(run: Callable[[], None]) -> None:  # a task's `run`
        run()

    @staticmethod
    def waitForDone(_ms: int = -1) -> bool:
        return True


@contextlib.contextmanager
def without_workers():
    pool, workers.QThreadPool = workers.QThreadPool, InlinePool
    try:
        yield
    finally:
        workers.QThreadPool = pool


def wait_until(condition: Callable[[], bool], timeout: float = TIMEOUT) -> None:
    """Run the event loop (so the heartbeat ticks) until `condition` holds."""
    loop = QEventLoop()
    check = QTimer(interval=20)
    deadline = time.perf_counter() + timeout
    met = []

    def poll() -> None:
        if condition():
            met.append(True)
            loop.quit()
        elif time.perf_counter() > deadline:
            loop.quit()

    check.timeout.connect(poll)
    check.start()
    loop.exec()
    check.stop()
    if not met:
        raise TimeoutError(f"still waiting after {timeout:.0f} s")


def measure(heart: Heartbeat, sampler: StallSampler, session: Session, start: Callable[[], None],
            ready: Callable[[], bool]) -> dict:
    """Start a job, wait until it is `ready` and no background work ran for SETTLE s; its stalls (s)."""
    wait_until(lambda: not session.jobs.running)
    idle_since: list[float | None] = [None]  # when the GUI thread first found the work over

    def settled() -> bool:
        now = time.perf_counter()
        if session.jobs.running or not ready():
            idle_since[0] = None
        elif idle_since[0] is None:
            idle_since[0] = now
        return idle_since[0] is not None and now - idle_since[0] >= SETTLE

    heart.beats.clear()
    sampler.take()
    t0 = time.perf_counter()
    start()
    wait_until(settled)
    end = idle_since[0]  # the settling wait is not part of the job
    beats = [b for b in heart.beats if b <= end]
    stalls = np.maximum(np.diff([t0, *beats, end]) - BEAT, 0.0)
    return {"seconds": end - t0, "max": stalls.max(), "p99": np.percentile(stalls, 99), "calls": sampler.take()}


def jobs(session: Session, editor: ImageEditor, viewer: Viewer3D, path: Path) -> dict[str, tuple]:
    """Job name → (start, ready): each started through the GUI's own code path."""
    def open_project() -> None:
        session.open(path)

    def extract() -> None:
        editor._extractor = Extractor()  # no ray tracer cached from an earlier run: both sides build it
        editor.extract(all_photos=True)

    def maps() -> None:
        viewer.maps_panel.compute()

    return {
        "open project (mesh, photo)": (open_project, lambda: viewer.mesh is not None
                                       and editor.view.pyramid is not None),
        "extract all photos to 3D": (extract, lambda: True),
        "auto-trace the photo": (lambda: editor.autotrace.run(whole=True), lambda: True),
        "intensity maps (compute)": (maps, lambda: True),
    }


def run(path: Path, words: list[str]) -> dict[str, dict[str, dict]]:
    app = QApplication.instance() or QApplication(sys.argv[:1])
    heart = Heartbeat()
    sampler = StallSampler(heart)
    session = Session()
    session.open(path)
    editor = ImageEditor(session)
    editor.show()
    viewer = Viewer3D(session, offscreen=True)
    viewer.resize(1280, 800)
    viewer.show()
    wait_until(lambda: viewer.mesh is not None and editor.view.pyramid is not None)
    app.processEvents()
    results: dict[str, dict[str, dict]] = {}
    for name, (start, ready) in jobs(session, editor, viewer, path).items():
        if words and not any(word in name for word in words):
            continue
        results[name] = {"workers": measure(heart, sampler, session, start, ready)}
        with without_workers():
            results[name]["GUI thread"] = measure(heart, sampler, session, start, ready)
        editor._extracting = None  # the inline task ended before `extract` stored it as running
    session.close()
    return results


def main() -> int:
    from engine.demo import run_demo

    parser = argparse.ArgumentParser(description=__doc__.partition("\n")[0])
    parser.add_argument("--demo", type=Path, help="build the demo here once and reuse it")
    parser.add_argument("words", nargs="*", help="only the jobs whose name has one of these words")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as scratch:
        folder = args.demo or Path(scratch)
        t0 = time.perf_counter()
        if not (folder / "demo.tracemap").exists():
            run_demo(folder, say=lambda _: None)
        print(f"demo ready in {time.perf_counter() - t0:.0f} s; {os.cpu_count()} CPUs, "
              f"load {os.getloadavg()[0]:.1f}")
        results = run(folder / "demo.tracemap", args.words)
    print(f"{'job':28s} {'side':11s} {'job s':>7s} {'max stall ms':>13s} {'99% stall ms':>13s}")
    worst = 0.0
    for name, sides in results.items():
        for side, r in sides.items():
            print(f"{name:28s} {side:11s} {r['seconds']:7.2f} {r['max'] * 1000:13.0f} {r['p99'] * 1000:13.0f}")
        worst = max(worst, sides["workers"]["max"])
        print(f"{'':28s} ratio workers/GUI thread: max stall "
              f"{sides['workers']['max'] / sides['GUI thread']['max']:.2f}")
        for call, seconds in sides["workers"]["calls"]:
            print(f"{'':28s} with workers, stalled {seconds:.2f} s in {call}")
    ok = worst <= 0.1
    print("target (no GUI-thread stall over 100 ms while work runs):", "met" if ok else "NOT met")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
