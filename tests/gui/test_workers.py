"""Background tasks: progress reaches the GUI thread, Cancel stops the engine, errors arrive as signals."""

import threading
import time

import PySide6
from PySide6.QtWidgets import QPushButton

from engine.errors import InputError
from tracemap_gui.workers import Jobs, ProgressPanel, Task


def counting(n, *, progress, pause=0.0):
    for k in range(n):
        progress(k / n, f"step {k}")
        time.sleep(pause)
    return threading.current_thread().name


def test_a_task_runs_off_the_gui_thread_and_reports_progress(qtbot):
    jobs = Jobs()
    task = Task("count", counting, 5, pause=0.06)
    seen = []
    task.signals.progress.connect(lambda f, m: seen.append((f, m, threading.current_thread().name)))
    with qtbot.waitSignal(task.signals.done, timeout=5000) as done:
        with qtbot.waitSignal(jobs.busy) as busy:
            jobs.start(task)
    assert busy.args == [True]
    assert done.args[0] != threading.current_thread().name
    assert seen and all(thread == threading.current_thread().name for _, _, thread in seen)
    qtbot.waitUntil(lambda: not jobs.running)


def test_cancel_stops_the_engine_at_its_next_progress_report(qtbot):
    jobs = Jobs()
    task = Task("long", counting, 10_000, pause=0.01)
    panel = ProgressPanel(jobs)
    qtbot.addWidget(panel)
    got = []
    task.signals.done.connect(got.append)
    with qtbot.waitSignal(task.signals.cancelled, timeout=5000):
        jobs.start(task)
        qtbot.waitUntil(panel.isVisible)
        panel.findChild(QPushButton, "cancel-task").click()
    qtbot.waitUntil(lambda: not panel.isVisible())
    assert got == []


def test_errors_arrive_as_signals(qtbot):
    def broken(*, progress):
        raise InputError("photo.jpg", "cannot read")

    task = Task("broken", broken)
    with qtbot.waitSignal(task.signals.failed, timeout=5000) as failed:
        Jobs().start(task)
    assert isinstance(failed.args[0], InputError)


def test_cancel_all_drops_results(qtbot):
    jobs = Jobs()
    task = Task("quick", counting, 3, pause=0.05)
    got = []
    task.signals.done.connect(got.append)
    jobs.start(task)
    jobs.cancel_all()
    qtbot.waitUntil(lambda: not jobs.running, timeout=5000)
    assert got == []


def test_a_task_cancelled_before_it_runs_reports_cancelled(qtbot):
    task = Task("t", counting, 3)
    task.cancel()
    with qtbot.waitSignal(task.signals.cancelled):
        task.run()


class _Input:
    """A stand-in for a task's inputs (traces, plots, a mesh), to watch for with a weak reference."""


def test_an_ended_task_keeps_neither_itself_nor_its_inputs(qtbot):
    """Up to session 15 every task was kept for good with its arguments: PySide6 keeps a QRunnable that the
    pool does not delete, and a slot holding the task is a cycle through Qt's connection."""
    import gc
    import weakref

    from PySide6.QtCore import QCoreApplication, QEvent, QThreadPool

    def work(data, *, progress, fail=False):
        if fail:
            raise InputError("photo.jpg", "cannot read")
        return len(str(data))

    jobs, kept = Jobs(), []
    for fail in (False, True):
        data = _Input()
        task = Task("work", work, data, fail=fail)
        task.signals.done.connect(lambda result, task=task: task.title)  # a slot holding its task, as panels do
        task.signals.failed.connect(lambda exc, task=task: task.title)
        with qtbot.waitSignal(task.signals.ended, timeout=5000):
            jobs.start(task)
        kept += [weakref.ref(task), weakref.ref(data)]
        del task, data
    qtbot.waitUntil(lambda: not jobs.running)
    # The worker may still be leaving `run` (its frame holds the task) when `ended` arrives: CI's loaded
    # machine caught that once, so wait for the pool before looking.
    assert QThreadPool.globalInstance().waitForDone(5000)
    QCoreApplication.sendPostedEvents(None, QEvent.Type.DeferredDelete.value)
    gc.collect()
    alive = [ref() is not None for ref in kept]
    if PySide6.__version_info__ < (6, 12):  # 6.7 keeps the slots of a failed task (6.8-6.11 not measured)
        alive[2] = False
    assert alive == [False] * 4
