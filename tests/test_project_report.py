"""`tracemap info`: the report against the project's own contents, stale results, missing inputs, next steps."""

import dataclasses
import json
import shutil

import pytest

from engine.cli import main
from engine.io import read_traces_csv
from engine.project import SCHEMA_VERSION, Project, new_project
from engine.project_report import project_report, report_lines


@pytest.fixture
def demo_copy(quick_demo, tmp_path):
    shutil.copytree(quick_demo / "data", tmp_path / "data")
    shutil.copy2(quick_demo / "demo.tracemap", tmp_path / "demo.tracemap")
    return tmp_path / "demo.tracemap"


def test_the_report_says_what_the_project_holds(demo_copy, capsys):
    with Project.open(demo_copy) as project:
        report = project_report(project)
        traces3d, traces2d, sets = project.traces3d(), project.traces2d(), project.result("sets")
    assert report["traces3d"]["n"] == len(traces3d) and report["traces2d"]["n"] == len(traces2d)
    assert report["schema"] == SCHEMA_VERSION and report_lines(report)[0] == f"{demo_copy} (schema {SCHEMA_VERSION})"
    assert report["traces2d"]["by_source"] == {"manual": len(traces2d)} and report["traces2d"]["photos"] == 3
    assert report["traces2d"]["by_photo"] == {name: sum(t.image == name for t in traces2d)
                                              for name in sorted({t.image for t in traces2d})}
    assert report["traces3d"]["length_m"] == pytest.approx(sum(t.surface_length for t in traces3d))
    assert [(s["id"], s["n"]) for s in report["sets"]] == [(s["id"], s["n"]) for s in sets]
    for ours, stored in zip(report["sets"], sets):  # not registered: the stored orientations as they are
        assert ours["dip"] == pytest.approx(stored["dip"], abs=1e-6)
        assert ours["dip_direction"] == pytest.approx(stored["dip_direction"], abs=1e-6)
    assert report["results"] == dict.fromkeys(("sets", "topology", "lengths", "intensity"), "stored")
    assert report["samples"] == {"facets": 0, "scanlines": 1, "scan_circles": 0}
    assert report["inputs"]["photos_unlinked"] == [] and report["inputs"]["mesh"]["problem"] is None
    assert report["next"].startswith("tracemap export")
    parents = {p for t in traces3d for p in t.parents}
    assert sum(report["traces2d"]["not_in_3d"].values()) == sum(t.id not in parents for t in traces2d)
    assert main(["info", str(demo_copy)]) == 0
    said = capsys.readouterr().out.splitlines()
    assert said == report_lines(report)
    assert next(line for line in said if line.startswith("3D traces:")) == (f"3D traces: {len(traces3d)}, {len(traces3d)} oriented, {len(traces3d)} in sets, "
                       f"{report['traces3d']['length_m']:.1f} m of trace")
    assert "samples: 0 facets, 1 scanline, 0 scan circles" in said
    waiting = sum(report["traces2d"]["not_in_3d"].values())
    assert waiting == 0 or any(line.startswith(f"  {waiting} 2D trace") for line in said)
    assert main(["info", str(demo_copy), "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == json.loads(json.dumps(report))


def test_an_older_project_is_reported_as_it_is(demo_copy):
    from tests.test_project import as_version

    as_version(demo_copy, 1)
    with Project.open(demo_copy) as project:
        report = project_report(project)
    assert report["schema"] == 1 and report["samples"] == {"facets": 0, "scanlines": 0, "scan_circles": 0}
    assert report_lines(report)[0] == f"{demo_copy} (schema 1, upgraded to {SCHEMA_VERSION} by the next edit)"


def test_results_older_than_the_traces_are_out_of_date(demo_copy):
    with Project.open(demo_copy) as project:
        traces = project.traces3d()
        with project.transaction() as db:  # as a trace edit leaves them: one trace moved to another set
            project.update_traces3d([dataclasses.replace(traces[0], set_id=(traces[0].set_id + 1) % 2)], db)
        report = project_report(project)
    assert report["results"]["sets"] == "out of date" and report["results"]["lengths"] == "out of date"
    assert report["results"]["topology"] == "stored"
    assert report["next"] == "tracemap orient (orientations and sets)"


def test_inputs_moved_away_are_said_not_raised(demo_copy):
    photo = next((demo_copy.parent / "data" / "images").iterdir())
    photo.rename(photo.with_name("elsewhere.png"))
    (demo_copy.parent / "data" / "mesh.ply").rename(demo_copy.parent / "data" / "moved.ply")
    with Project.open(demo_copy) as project:
        report = project_report(project)
    lines = report_lines(report)
    assert "mesh.ply" in report["inputs"]["mesh"]["problem"] and lines[1].startswith("mesh: ")
    assert len(report["inputs"]["photo_problems"]) == 1 and photo.name in report["inputs"]["photo_problems"][0]
    assert report["next"].startswith("put the mesh back")


def test_the_next_step_follows_the_pipeline(quick_demo, tmp_path):
    data = quick_demo / "data"
    with new_project(tmp_path / "site.tracemap", data / "mesh.ply", data / "cameras.json") as project:
        report = project_report(project)
        assert report["inputs"]["photos_unlinked"] == sorted(project.cameras())  # no photos folder given
        assert report["next"].startswith("trace fractures on the photos")
        assert report["results"] == dict.fromkeys(("sets", "topology", "lengths", "intensity"), "not yet")
        traces = read_traces_csv(data / "traces2d_true.csv", project.cameras(local=False))
        first = sorted({t.image for t in traces})[0]
        project.add_traces2d([t for t in traces if t.image == first])
        partial = project_report(project)
        assert partial["next"].startswith("tracemap extract")
        assert partial["traces2d"]["untraced"] == sorted(set(project.cameras()) - {first})
        assert f"  no traces yet on 2 photos: {', '.join(partial['traces2d']['untraced'])}" in report_lines(partial)
    assert "cameras: 3, 3 without a photo linked" in report_lines(report)
