"""The engine is a plain library: importing any of its modules loads no Qt (DESIGN.md "Layout")."""

import json
import subprocess
import sys
from pathlib import Path

ENGINE = Path(__file__).resolve().parents[1] / "engine"
QT = ("PySide6", "PyQt5", "PyQt6", "pyvistaqt", "qtpy", "shiboken6")


def test_importing_every_engine_module_loads_no_qt():
    modules = sorted(".".join(p.relative_to(ENGINE.parent).with_suffix("").parts).removesuffix(".__init__")
                     for p in ENGINE.rglob("*.py"))
    script = ("import importlib, json, sys\n"
              f"for name in {modules!r}:\n"
              "    importlib.import_module(name)\n"
              "print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in " + repr(QT) + ")))")
    # a fresh interpreter: this test process has Qt loaded already
    out = subprocess.run([sys.executable, "-c", script], cwd=ENGINE.parent, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert len(modules) > 20
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []
