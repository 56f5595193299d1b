"""A spin box for a length the user types (a radius, a reach, a tolerance), in the readouts' frame."""

from __future__ import annotations

from PySide6.QtWidgets import QDoubleSpinBox, QWidget


def length_box(parent: QWidget, name: str, tip: str, *, low: float, high: float, decimals: int,
               step: float | None = None, unit: str = "m") -> QDoubleSpinBox:
    """A QDoubleSpinBox named `name` (for tests and saved layouts) from `low` to `high` in `unit`."""
    box = QDoubleSpinBox(parent)
    box.setObjectName(name)
    box.setRange(low, high)
    box.setDecimals(decimals)
    if step is not None:
        box.setSingleStep(step)
    box.setSuffix(f" {unit}")
    box.setToolTip(tip)
    return box
