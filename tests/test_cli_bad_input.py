"""The command line against bad input and failing output: one clear message, and nothing lost or half-written
(DESIGN.md "Command line"). The cases come from a fuzz of every command."""

import errno
import os
import subprocess
import sys

import pytest

import engine.io
from engine.cli import main
from engine.extract import MIN_VERTICES
from engine.project import Project
from tests.test_cli import new_project, survey  # noqa: F401  (a fixture)


@pytest.fixture
def project(survey):  # noqa: F811
    d, _ = survey
    assert new_project(d) == 0
    assert main(["import-traces", str(d / "p.tracemap"), str(d / "traces.csv")]) == 0
    return d, str(d / "p.tracemap")


def test_export_onto_a_folder_of_an_output_name_writes_nothing(project, capsys):
    d, path = project
    (d / "out" / "traces.csv").mkdir(parents=True)
    (d / "out" / "summary.json").write_text("earlier")
    assert main(["export", path, str(d / "out")]) == 2
    err = capsys.readouterr().err
    assert "traces.csv: is a folder where the output writes a file" in err
    assert sorted(p.name for p in (d / "out").iterdir()) == ["summary.json", "traces.csv"]
    assert (d / "out" / "summary.json").read_text() == "earlier"


def test_export_into_a_file_is_refused(project, capsys):
    d, path = project
    (d / "out").write_text("a file")
    assert main(["export", path, str(d / "out")]) == 2
    assert "out: is a file; the output must go to a folder" in capsys.readouterr().err


def test_failed_export_removes_the_folders_it_made(project, monkeypatch):
    d, path = project

    def full(path, data):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(engine.io, "write_json", full)
    assert main(["export", path, str(d / "new" / "out")]) == 2
    assert not (d / "new").exists()


def output_failing_on_c(out, names, monkeypatch):
    """Write `names` as one output into `out`, c.csv failing to take its place (an I/O error)."""
    real = os.replace

    def replace(src, dst):
        if str(src).endswith("c.csv"):
            raise OSError(errno.EIO, "Input/output error", str(dst))
        real(src, dst)

    monkeypatch.setattr(engine.io.os, "replace", replace)
    with pytest.raises(OSError), engine.io.atomic_directory(out) as scratch:
        for name in names:
            (scratch / name).write_text("new")


def test_a_file_failing_to_take_its_place_puts_back_the_ones_replaced(tmp_path, monkeypatch):
    out = tmp_path / "out"
    out.mkdir()
    for name in ("a.csv", "b.csv"):
        (out / name).write_text("earlier")
    output_failing_on_c(out, ("a.csv", "b.csv", "c.csv"), monkeypatch)
    assert sorted(p.name for p in out.iterdir()) == ["a.csv", "b.csv"]
    assert {p.read_text() for p in out.iterdir()} == {"earlier"}


class _Broken:
    def __init__(self, error):
        self.error = error

    def write(self, text):
        raise self.error

    def flush(self):
        raise self.error


@pytest.mark.parametrize("error, code", [(OSError(errno.ENOSPC, "No space left on device"), 2),
                                         (BrokenPipeError(errno.EPIPE, "Broken pipe"), 0)])
def test_a_report_that_cannot_be_printed_does_not_undo_the_command(survey, capsys, monkeypatch, error, code):  # noqa: F811
    d, _ = survey
    assert new_project(d) == 0
    capsys.readouterr()
    monkeypatch.setattr(sys, "stdout", _Broken(error))
    assert main(["import-traces", str(d / "p.tracemap"), str(d / "traces.csv")]) == code
    err = capsys.readouterr().err
    assert ("the command completed (its changes are saved), but its report could not be written" in err) == (code == 2)
    assert "nothing was changed" not in err
    with Project.open(d / "p.tracemap") as p:
        assert len(p.traces2d()) == 3


def test_stdout_on_a_full_disk_in_a_real_process(project):
    d, path = project
    with open("/dev/full", "w") as full:
        run = subprocess.run([sys.executable, "-m", "engine.cli", "import-traces", path, str(d / "traces.csv")],
                             stdout=full, stderr=subprocess.PIPE, text=True)
    assert run.returncode == 2
    assert "report could not be written" in run.stderr and "Exception ignored" not in run.stderr
    with Project.open(path) as p:
        assert len(p.traces2d()) == 6


@pytest.mark.parametrize("args, message", [
    (["orient", "P", "--k-threshold", "nan"], "argument --k-threshold: expected a number ≥ 0, got 'nan'"),
    (["orient", "P", "--k-threshold", "-1"], "argument --k-threshold: expected a number ≥ 0, got '-1'"),
    (["orient", "P", "--sets", "0"], "argument --sets: expected an integer ≥ 1, got '0'"),
    (["analyse", "P", "--bootstrap", "-5"], "argument --bootstrap: expected an integer ≥ 0, got '-5'"),
    (["analyse", "P", "--radius", "inf"], "argument --radius: expected a number > 0, got 'inf'"),
    (["analyse-map", "T", "A", "-o", "O", "--snap", "0"], "argument --snap: expected a number > 0, got '0'"),
    (["extract", "P", "--spacing", "0"], "argument --spacing: expected a number > 0, got '0'"),
    (["extract", "P", "--min-run", str(MIN_VERTICES - 1)],
     f"argument --min-run: expected an integer ≥ {MIN_VERTICES}, got '{MIN_VERTICES - 1}'"),
    (["merge", "P", "--tolerance", "nan"], "argument --tolerance: expected a number > 0, got 'nan'"),
    (["facet", "P", "--point", "1", "nan", "2", "--radius", "1"], "argument --point: expected a number, got 'nan'"),
    (["render", "P", "-o", "x.png", "--size", "100000", "10"], "expected an integer ≥ 16 and ≤ 16384, got '100000'"),
    (["render", "P", "-o", "x.png", "--size", "8", "8"], "argument --size: expected an integer ≥ 16 and ≤ 16384, got '8'"),
    (["orient", "P", "--sets", "1" + "0" * 400], "argument --sets: expected an integer ≥ 1, got '1000"),
    (["new", "P", "--mesh", "M", "--cameras", "C", "--image-size", "640.5", "480"],
     "argument --image-size: expected an integer > 0, got '640.5'"),
])
def test_option_values_out_of_range_are_refused_before_any_work(args, message, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(args)
    assert exit_.value.code == 2 and message in capsys.readouterr().err


def test_options_that_would_be_ignored_are_refused(project, capsys):
    d, path = project
    assert main(["render", path, "-o", str(d / "x.png"), "--map", "p21"]) == 2
    assert "use it with --color-by p21 or p32, not set" in capsys.readouterr().err
    assert main(["new", str(d / "q.tracemap"), "--mesh", str(d / "wall.obj"), "--cameras", str(d / "cameras.json"),
                 "--image-size", "800", "600"]) == 2
    assert "an image size is for Bundler, NVM and OpenMVS files" in capsys.readouterr().err
    assert not (d / "q.tracemap").exists() and not (d / "x.png").exists()


def test_a_facet_point_far_off_the_mesh_is_a_clear_error(project, capsys):
    d, path = project
    assert main(["facet", path, "--point", "1e200", "0", "0", "--radius", "0.3"]) == 2
    assert "the point is 1e+200 m or more outside the mesh's bounding box" in capsys.readouterr().err


def test_a_traces_csv_of_only_a_header_is_refused(project, capsys):
    d, path = project
    (d / "empty.csv").write_text("image,trace,u,v\n")
    assert main(["import-traces", path, str(d / "empty.csv")]) == 2
    assert "empty.csv: no rows below the header" in capsys.readouterr().err


def test_an_error_of_the_analysis_names_the_project(project, capsys, monkeypatch):
    from engine.errors import InputError

    d, path = project

    def fails(*args, **kwargs):
        raise InputError(None, "none of the 2 traces has the 3 vertices a plane needs")

    monkeypatch.setattr("engine.analysis.orient_and_classify", fails)
    assert main(["extract", path]) == 0
    assert main(["orient", path]) == 2
    assert f"tracemap orient: error: {path}: none of the 2 traces" in capsys.readouterr().err


def test_a_rolled_back_output_puts_back_a_relative_symlink(tmp_path, monkeypatch):
    out = tmp_path / "out"
    out.mkdir()
    (out / "real_a.csv").write_text("earlier")
    (out / "a.csv").symlink_to("real_a.csv")  # relative: it resolves only where it stands
    output_failing_on_c(out, ("a.csv", "c.csv"), monkeypatch)
    assert (out / "a.csv").is_symlink() and (out / "a.csv").read_text() == "earlier"
    assert sorted(p.name for p in out.iterdir()) == ["a.csv", "real_a.csv"]
