"""The photo view on a 24 MP photo, side by side with the obvious peer: one QGraphicsPixmapItem of the photo.

Targets (issue 5): first view ≤ 2 s (from asking for the photo to the first frame showing it, reading the
JPEG included), and every pan or zoom frame ≤ 50 ms, with 500 traces of 300 vertices drawn over the photo.

Run:  python tests/benchmarks/bench_photo_view.py      (offscreen; a 1600 × 1000 view)
A frame is timed from the step (scroll or zoom) until the event loop has painted it: tiles (made or cached),
traces and the tool overlay.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from PySide6.QtCore import QRectF, Qt  # noqa: E402
from PySide6.QtGui import QColor, QImage, QPixmap  # noqa: E402
from PySide6.QtWidgets import QApplication, QGraphicsPixmapItem, QGraphicsScene, QGraphicsView  # noqa: E402

import tracemap_gui  # noqa: E402,F401 - its PySide6 work-round must come first
from tracemap_gui.photo_view import PhotoView, read_photo  # noqa: E402
from tracemap_gui.trace_layer import PolylineSetItem, cosmetic_pen, polyline_path  # noqa: E402

SIZE = (6000, 4000)  # 24 MP
VIEW = (1600, 1000)
TRACES, VERTICES = int(os.environ.get("BENCH_TRACES", 500)), 300


def synthetic_photo(path: Path, seed: int = 0) -> None:
    """Rock-like texture with dark wiggly lines, as a JPEG of quality 92."""
    rng = np.random.default_rng(seed)
    w, h = SIZE
    small = rng.normal(128, 40, (h // 16, w // 16, 3)).astype(np.float32)
    image = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    image += rng.normal(0, 12, (h, w, 3)).astype(np.float32)
    image = np.clip(image, 0, 255).astype(np.uint8)
    for polyline in traces(seed):
        cv2.polylines(image, [polyline.astype(np.int32).reshape(-1, 1, 2)], False, (30, 30, 30), 3)
    cv2.imwrite(str(path), image, [cv2.IMWRITE_JPEG_QUALITY, 92])


def traces(seed: int = 0) -> list[np.ndarray]:
    """Wavy lines with a vertex every pixel and half a pixel of jitter, as auto-trace and guided curves make."""
    rng = np.random.default_rng(seed + 1)
    s = np.arange(VERTICES, dtype=np.float64)
    out = []
    for _ in range(TRACES):
        start = rng.uniform([400, 400], [SIZE[0] - 400, SIZE[1] - 400])
        angle = rng.uniform(0, np.pi)
        along = np.column_stack([np.cos(angle), np.sin(angle)])
        across = np.column_stack([-np.sin(angle), np.cos(angle)])
        wave = 8 * np.sin(s / rng.uniform(20, 60) + rng.uniform(0, 6)) + rng.uniform(-0.5, 0.5, VERTICES)
        out.append(start + s[:, None] * along + wave[:, None] * across)
    return out


def add_traces(view: QGraphicsView) -> None:
    """The traces as the editor draws them (one PolylineSetItem), or, for the peer, one path item each."""
    pen = cosmetic_pen(QColor(255, 190, 0), 2.0)
    if isinstance(view, PhotoView):
        item = PolylineSetItem()
        item.set_polylines(dict(enumerate(traces())), dict.fromkeys(range(TRACES), pen))
        view.scene().addItem(item)
        return
    for polyline in traces():
        view.scene().addPath(polyline_path(polyline), pen)


def frames(app: QApplication, view: QGraphicsView) -> dict[str, list[float]]:
    """Times (ms) of pan frames at 0.4× and 1:1, and of zoom frames from the fitted zoom to 4× and back."""
    def timed(step) -> float:
        """The step and the repaint it causes (a pan scrolls the old frame and paints the exposed strip)."""
        app.processEvents()
        start = time.perf_counter()
        step()
        app.processEvents()
        return (time.perf_counter() - start) * 1000

    out: dict[str, list[float]] = {"pan (0.4×)": [], "pan (1:1)": [], "zoom": []}
    bar = view.horizontalScrollBar()
    for name, scale in (("pan (0.4×)", 0.4), ("pan (1:1)", 1.0)):
        view.resetTransform()
        view.scale(scale, scale)
        view.centerOn(SIZE[0] / 2, SIZE[1] / 2)
        step = 90  # screen pixels per frame, a brisk drag; turn back at the ends
        for _ in range(40):
            if not bar.minimum() <= bar.value() + step <= bar.maximum():
                step = -step
            out[name].append(timed(lambda: bar.setValue(bar.value() + step)))
    view.fitInView(QRectF(0, 0, *SIZE))
    for k in range(24):
        factor = 1.25 if k < 12 else 0.8  # 0.27× … 4× and back, about the centre
        out["zoom"].append(timed(lambda: view.scale(factor, factor)))
    return out


def ours(app: QApplication, path: Path) -> tuple[float, dict]:
    view = PhotoView()
    view.resize(*VIEW)
    view.show()
    add_traces(view)
    app.processEvents()
    start = time.perf_counter()
    view.show_photo("bench", SIZE, path)
    while view.pyramid is None:
        app.processEvents()
        time.sleep(0.001)
    view.viewport().repaint()
    first = time.perf_counter() - start
    return first, frames(app, view)


def peer(app: QApplication, path: Path) -> tuple[float, dict]:
    view = QGraphicsView()
    view.setScene(QGraphicsScene(view))
    view.resize(*VIEW)
    view.show()
    add_traces(view)
    app.processEvents()
    start = time.perf_counter()
    image = cv2.cvtColor(read_photo(path), cv2.COLOR_BGR2RGB)
    pixmap = QPixmap.fromImage(QImage(image.data, image.shape[1], image.shape[0], image.strides[0],
                                      QImage.Format.Format_RGB888))
    item = QGraphicsPixmapItem(pixmap)
    item.setTransformationMode(Qt.TransformationMode.SmoothTransformation)
    view.scene().addItem(item)
    view.fitInView(QRectF(0, 0, *SIZE))
    view.viewport().repaint()
    first = time.perf_counter() - start
    return first, frames(app, view)


def summary(name: str, first: float, times: dict[str, list[float]]) -> dict[str, float]:
    print(f"{name}: first view {first:.2f} s")
    worst = {}
    for kind, ms in times.items():
        ms = np.array(ms)
        worst[kind] = ms.max()
        print(f"  {kind:13s} median {np.median(ms):6.1f} ms   95% {np.percentile(ms, 95):6.1f} ms   "
              f"max {ms.max():6.1f} ms")
    return worst


def main() -> int:
    app = QApplication(sys.argv[:1])
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "photo24mp.jpg"
        synthetic_photo(path)
        print(f"{SIZE[0]}×{SIZE[1]} JPEG ({path.stat().st_size / 1e6:.1f} MB), {TRACES} traces of {VERTICES} "
              f"vertices, view {VIEW[0]}×{VIEW[1]}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}")
        first, times = ours(app, path)
        worst = summary("tiled pyramid (tracemap)", first, times)
        peer_first, peer_times = peer(app, path)
        peer_worst = summary("one QGraphicsPixmapItem (peer)", peer_first, peer_times)
    print(f"ratio to peer: first view {first / peer_first:.2f}×, worst frame "
          + ", ".join(f"{k} {worst[k] / peer_worst[k]:.2f}×" for k in worst))
    ok = first <= 2.0 and max(worst.values()) <= 50.0
    print("targets (first view ≤ 2 s, every frame ≤ 50 ms):", "met" if ok else "NOT met")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
