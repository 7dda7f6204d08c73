"""Progress on stderr: off when stderr is no terminal (scripts, CI, these tests), one helper everywhere.

No timers: the bar is forced on into a buffer (``TerminalProgress(enabled=True, file=...)``) and the stages it
drew are read back; a stage change always redraws, so what is asserted does not depend on timing.
"""
import io
import re

from selfcal.cli.main import main
from selfcal.core.progress import TerminalProgress, quiet
from selfcal.io.recording import read_recording
from selfcal.pipelines.ship import smooth_ship
from selfcal.sim.ship import ShipScenario


def short_voyage(tmp_path):
    """One minute of heave (about a second to smooth)."""
    return ShipScenario(kind="heave", duration_s=60.0, seed=5).write(tmp_path / "voyage", seed=6)


def test_smooth_ship_reports_its_stages_to_the_bar(tmp_path):
    rec = read_recording(short_voyage(tmp_path))
    stages = []
    smooth_ship(rec, progress=lambda stage, done=None, total=None: stages.append(stage))
    assert stages[:4] == ["IMU and speed on one time base", "keyframes", "build the graph", "least squares"]
    assert stages[4].startswith("least squares (iteration 1 done, error ")  # GTSAM's iteration hook
    drawn = io.StringIO()
    with TerminalProgress("smooth ship", enabled=True, file=drawn) as progress:
        smooth_ship(rec, progress=progress)
    text = drawn.getvalue()
    for stage in stages:
        assert f"smooth ship: {stage}" in text


def test_a_counted_loop_draws_a_bar_with_its_total():
    drawn = io.StringIO()
    with TerminalProgress("measure encoder", enabled=True, file=drawn) as progress:
        for i in range(12):
            progress("frames", i, 12)
    assert "measure encoder: frames:" in drawn.getvalue() and "0/12" in drawn.getvalue()


def test_the_bar_is_off_when_stderr_is_no_terminal():
    drawn = io.StringIO()  # not a tty: tqdm's disable=None turns the bar off
    with TerminalProgress("qc", file=drawn) as progress:
        progress("spheres")
        progress("frames", 3, 10)
    assert drawn.getvalue() == ""
    assert quiet("anything", 1, 2) is None  # the library's default says nothing


def test_cli_prints_results_with_units_and_nothing_on_a_non_terminal_stderr(tmp_path, capsys):
    rec = short_voyage(tmp_path)
    assert main(["smooth", "ship", str(rec), "--out", str(tmp_path / "a.tum")]) == 0
    captured = capsys.readouterr()
    assert captured.err == ""
    summary, *bias, written = captured.out.splitlines()
    number = r"[-+]?[0-9.]+(?:e[-+][0-9]+)?"
    assert re.fullmatch(rf"[0-9]+ attitudes over 60 s in {number} s \(batch\); final gyro bias:", summary), summary
    assert len(bias) == 3
    for axis, line in zip("xyz", bias):  # each axis with its sigma and unit, or flagged (issue 16, item 6)
        assert re.fullmatch(rf"  gyro bias {axis}: ({number} \+- {number} deg/h \(1 sigma\)|NOT DETERMINED by this "
                            rf"voyage \(value {number}, sigma {number} deg/h, bound 5 deg/h; not a result\): .+)",
                            line), line
    assert written == f"trajectory: {tmp_path / 'a.tum'}"
