"""`slamreplay record` sub-commands come from the entry-point group slamreplay.importers, a user's as the built-ins."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from conftest import make_distribution

from slamreplay.api.cli.command import main
from slamreplay.recorder.errors import RecorderError
from slamreplay.recorder.plugins import refresh
from slamreplay.recorder.sources import get_importer, importer_plugins
from slamreplay.replay.engine.reader import RecordingReader

BUILTINS = {"images", "mrclam", "ros2", "sim-corridor", "sim-landmarks", "sim-seabed", "victoria-park"}

CSV_IMPORTER = '''
import csv
from pathlib import Path

from slamreplay.recorder import OdometryPose, Recorder
from slamreplay.recorder.errors import RecorderError


class CsvOdometry:
    """Odometry poses from a CSV file of t_s,x_m,y_m,yaw_rad rows."""

    name = "csv-odometry"
    help = "odometry poses from a CSV file"
    description = "Record each row t_s,x_m,y_m,yaw_rad of CSV as an /odom pose."
    progress_label = "importing CSV"

    def add_arguments(self, parser):
        parser.add_argument("csv", help="the CSV file")
        parser.add_argument("--out", required=True, help="the .mcap file to write (must not exist)")

    def record(self, options, progress, log):
        rows = list(csv.reader(Path(options["csv"]).read_text().splitlines()))
        try:
            poses = [(round(float(t) * 1e9), float(x), float(y), float(yaw)) for t, x, y, yaw in rows]
        except ValueError as err:
            raise RecorderError(f"{options['csv']}: not t_s,x_m,y_m,yaw_rad rows ({err})") from None
        with Recorder(Path(options["out"]), source={"importer": self.name}) as rec:
            for k, (t, x, y, yaw) in enumerate(poses):
                rec.write("/odom", OdometryPose(t, x, y, yaw))
                progress(k + 1, len(poses))
        return f"{len(poses)} odometry poses"


class NoRecord:
    name = "no-record"
    help = description = progress_label = "x"

    def add_arguments(self, parser):
        pass
'''


@pytest.fixture
def importers(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A fake distribution `csv-importers 0.3` with one working importer and three broken ones."""
    root = tmp_path / "site"
    make_distribution(root, "csv-importers", "0.3", {
        "csv-odometry": "csvimp.main:CsvOdometry",
        "no-record": "csvimp.main:NoRecord",
        "gone": "csvimp.gone:Importer",
        "renamed": "csvimp.main:CsvOdometry",
    }, {"csvimp.__init__": "", "csvimp.main": CSV_IMPORTER}, group="slamreplay.importers")
    monkeypatch.syspath_prepend(str(root))
    refresh()
    yield root
    refresh()
    for mod in [m for m in sys.modules if m == "csvimp" or m.startswith("csvimp.")]:
        del sys.modules[mod]


def test_builtin_importers_are_entry_points() -> None:
    """The seven built-in sources are entry points of slamreplay itself."""
    found = importer_plugins()
    assert set(found) >= BUILTINS and all(found[n].builtin and found[n].error is None for n in BUILTINS)
    assert get_importer("mrclam").progress_label == "importing MRCLAM"
    with pytest.raises(RecorderError, match="unknown importer 'nope'; known: images, mrclam"):
        get_importer("nope")


def test_user_importer_is_a_record_subcommand(importers: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """A third-party importer becomes `record csv-odometry`, with its own arguments, and writes a recording."""
    monkeypatch.setenv("COLUMNS", "250")  # help lines unwrapped
    with pytest.raises(SystemExit):
        main(["record", "--help"])
    out = capsys.readouterr().out
    assert "odometry poses from a CSV file [csv-importers 0.3]" in out and "sim-landmarks" in out
    assert "BROKEN (csv-importers 0.3): failed to import: ModuleNotFoundError" in out
    csv = tmp_path / "poses.csv"
    csv.write_text("".join(f"{k * 0.1},{k * 0.05},0,{k * 0.01}\n" for k in range(20)))
    code = main(["record", "csv-odometry", str(csv), "--out", str(tmp_path / "csv.mcap")])
    err = capsys.readouterr().err
    assert code == 0 and f"wrote {tmp_path / 'csv.mcap'}: 20 odometry poses" in err
    msgs = list(RecordingReader(tmp_path / "csv.mcap").messages())
    assert len(msgs) == 20 and np.allclose(msgs[-1].msg.xy_yaw, [0.95, 0.0, 0.19])
    csv.write_text("a,b,c,d\n")
    code = main(["record", "csv-odometry", str(csv), "--out", str(tmp_path / "bad.mcap")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "not t_s,x_m,y_m,yaw_rad rows" in err[0]


@pytest.mark.parametrize(("name", "reason"), [
    ("gone", "failed to import: ModuleNotFoundError: No module named 'csvimp.gone'"),
    ("no-record", "does not implement the Importer protocol (missing record)"),
    ("renamed", "is registered as 'renamed' but its class says name = 'csv-odometry'"),
])
def test_broken_importer_is_one_line_when_used(importers: Path, tmp_path: Path, name: str, reason: str,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    """Using a broken importer: exit 2, one line naming it, its distribution and why; the others still work."""
    code = main(["record", name, "whatever", "--out", str(tmp_path / "x.mcap")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert f"importer plugin '{name}'" in err[0] and "distribution csv-importers 0.3" in err[0] and reason in err[0]
    assert not (tmp_path / "x.mcap").exists()
    assert main(["record", "sim-landmarks", "--out", str(tmp_path / "ok.mcap"), "--duration-s", "5", "-q"]) == 0
