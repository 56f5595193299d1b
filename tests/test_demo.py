import csv
import json
import re

from engine.cli import main
from engine.demo import DEMO_OUTCROP, run_demo
from engine.synthetic import QUICK


def test_extraction_accuracy_on_the_synthetic_outcrop(tmp_path):
    """Issue 2 target: true 2D traces in, median ≤ 0.5 and 95th percentile ≤ 1.5 pixel footprints out."""
    error = run_demo(tmp_path, seed=3, outcrop_settings={**DEMO_OUTCROP, **QUICK}, say=lambda m: None)
    assert error.n_vertices > 1000
    assert error.median_footprints <= 0.5
    assert error.p95_footprints <= 1.5


def test_demo_command_writes_everything(tmp_path, capsys):
    assert main(["demo", "--headless", "--quick", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "3D error against the truth" in out
    # each set found is compared with the nearest generating set, by the angle between their mean poles
    found = re.search(r"sets: true .*; found (.*)", out).group(1)
    angles = [float(a) for a in re.findall(r"(\d+\.\d)° from \d+/\d{3}", found)]
    assert len(angles) >= 1 and all(0 <= a <= 90 for a in angles)
    for name in ("traces.csv", "trace_vertices.csv", "traces2d.csv", "summary.json"):
        assert (tmp_path / "export" / name).is_file()
    summary = json.loads((tmp_path / "export" / "summary.json").read_text())
    with open(tmp_path / "export" / "traces.csv") as f:
        assert len(list(csv.DictReader(f))) == summary["traces3d"]["total"] > 0
    for name in ("stereonet", "length_histogram", "kaplan_meier", "terminations", "summary"):
        assert (tmp_path / "plots" / f"{name}.png").is_file() and (tmp_path / "plots" / f"{name}.csv").is_file()
    assert f"-> {tmp_path / 'plots'}" in out
    # running it again starts afresh instead of failing on the existing project
    assert main(["demo", "--headless", "--quick", "--out", str(tmp_path)]) == 0
