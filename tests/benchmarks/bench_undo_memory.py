"""The memory a long editing session's undo history holds, side by side with a history without a budget.

Run:  python tests/benchmarks/bench_undo_memory.py [--edits N] [--vertices V] [--budget MB]
(offscreen; builds the quick demo project in a temporary folder). Each edit replaces every 3D trace by a
new set of V vertices in all (default 2M: a re-extraction of about 5 photos at the paper's pixel density),
as re-extracting does. Printed per side: the bytes Python holds after each edit (tracemalloc: the session's
caches, the history and everything else), the process's resident memory, the longest GUI-thread time of an
edit's push, the longest the GUI thread then waited while the history's writes ran on a worker, and undoing
every edit (spilled ones read back from
disk). Peer: the same session with no budget, i.e. every edit's traces in memory, as before session 16.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import numpy as np  # noqa: E402
from PySide6.QtCore import QThreadPool  # noqa: E402
from PySide6.QtWidgets import QApplication  # noqa: E402

import tracemap_gui  # noqa: E402,F401 - its PySide6 work-round must come first
from engine.demo import DEMO_OUTCROP, run_demo  # noqa: E402
from engine.synthetic import QUICK  # noqa: E402
from engine.traces import Trace3D  # noqa: E402
from tracemap_gui import commands  # noqa: E402
from tracemap_gui.session import Session  # noqa: E402


def rss() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def trace_set(rng: np.random.Generator, vertices: int, per_trace: int = 2000) -> list[Trace3D]:
    out = []
    for _ in range(vertices // per_trace):
        points = np.cumsum(rng.normal(0, 0.003, (per_trace, 3)), axis=0) + rng.uniform(0, 10, 3)
        out.append(Trace3D(0, points, rng.uniform(0, 1000, (per_trace, 2)), np.zeros(per_trace, np.int64),
                           np.zeros(per_trace, np.int32), ("photo_01",)))
    return out


def settle(app: QApplication, session: Session) -> float:
    """Wait for the history's writes; the longest pass of this 10 ms loop beyond its sleep (s): how long the
    GUI thread waited for the GIL while a worker pickled."""
    longest, last = 0.0, time.perf_counter()
    while session.undo_memory._writing is not None or not QThreadPool.globalInstance().waitForDone(0):
        app.processEvents()
        time.sleep(0.01)
        now = time.perf_counter()
        longest, last = max(longest, now - last - 0.01), now
    return longest


def run(app: QApplication, project: Path, edits: int, vertices: int, budget: int) -> None:
    session = Session(undo_memory=budget)
    session.open(project)
    rng = np.random.default_rng(0)
    tracemalloc.start()
    pushes, waits = [], []
    for k in range(edits):
        old, new = session.traces3d(), trace_set(rng, vertices)
        command = commands.ReplaceTraces3D(session, old, new, f"re-extract {k}")
        del old, new
        start = time.perf_counter()
        session.push(command)
        pushes.append(time.perf_counter() - start)
        del command
        waits.append(settle(app, session))
        held, _ = tracemalloc.get_traced_memory()
        print(f"  edit {k + 1}: Python holds {held / 2**20:7.0f} MB (history {session.undo_memory.held() / 2**20:5.0f} MB"
              f" in memory), resident {rss() / 2**20:6.0f} MB, push {pushes[-1]:.2f} s", flush=True)
    start = time.perf_counter()
    for _ in range(edits):
        session.undo_stack.undo()
    undo = time.perf_counter() - start
    print(f"  undo all {edits}: {undo:.1f} s ({undo / edits:.2f} s each); pushes {min(pushes):.2f}–{max(pushes):.2f} s;"
          f" longest GUI-thread wait after a push {max(waits) * 1000:.0f} ms")
    tracemalloc.stop()
    session.close()


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--edits", type=int, default=8)
    parser.add_argument("--vertices", type=int, default=2_000_000)
    parser.add_argument("--budget", type=float, default=256.0, help="MB")
    parser.add_argument("--side", choices=["tracemap", "peer"], help="one side only (a fresh process each)")
    args = parser.parse_args()
    app = QApplication(sys.argv[:1])
    with tempfile.TemporaryDirectory() as folder:
        run_demo(Path(folder), seed=3, outcrop_settings={**DEMO_OUTCROP, **QUICK}, say=lambda m: None)
        for side, budget in (("tracemap", int(args.budget * 2**20)), ("peer", sys.maxsize)):
            if args.side in (None, side):
                print(f"{side} (budget {'none' if budget == sys.maxsize else f'{args.budget:g} MB'}):", flush=True)
                run(app, Path(folder) / "demo.tracemap", args.edits, args.vertices, budget)


if __name__ == "__main__":
    main()
