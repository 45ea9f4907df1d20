"""What ``flocktrack.load`` and ``flocktrack export`` say of input that is not a recording, and without the
``analysis`` extra: one line, naming the file and what is wrong (or the extra to install); and that
``import flocktrack`` (and the command's parser) does not import pandas."""

import subprocess
import sys

import pytest

import flocktrack
from flocktrack.analysis import LoadError
from flocktrack.cli import main


def _foreign_mcap(path):
    """An MCAP file of another program: its own schema, channel, message and metadata."""
    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="other", library="other")
        schema = w.register_schema(name="other.Pose", encoding="jsonschema", data=b"{}")
        channel = w.register_channel(topic="/pose", message_encoding="json", schema_id=schema)
        w.add_message(channel_id=channel, log_time=1, publish_time=1, data=b'{"x": 1}')
        w.add_metadata("other", {"robot": "r2"})
        w.finish()


def _bad_input(kind: str, tmp_path):
    """(the path given, the file the line names, what it says)"""
    if kind == "missing":
        p = tmp_path / "nowhere"
        return p, p, "no such file or directory"
    if kind == "no recording":
        p = tmp_path / "run"
        p.mkdir()
        (p / "summary.json").write_text("{}")
        return p, p, "without a recording.mcap"
    if kind == "not mcap":
        p = tmp_path / "scenario.toml"
        p.write_text("[run]\nticks = 3\n")
        return p, p, "not an MCAP file"
    p = tmp_path / "other.mcap"
    _foreign_mcap(p)
    return p, p, "not a flocktrack recording"


@pytest.mark.parametrize("kind", ["missing", "no recording", "not mcap", "foreign mcap"])
def test_input_that_is_not_a_recording_is_one_line_naming_the_file(kind, tmp_path, capsys):
    given, named, what = _bad_input(kind, tmp_path)
    with pytest.raises(LoadError) as exc:
        flocktrack.load(given)
    line = str(exc.value)
    assert isinstance(exc.value, ValueError) and line.startswith(f"{named}: ") and what in line and "\n" not in line
    assert main(["export", str(given), "--out", str(tmp_path / "tables")]) == 2
    assert capsys.readouterr().err.splitlines() == [f"error: {line}"]
    assert not (tmp_path / "tables").exists()


def test_without_pandas_load_and_export_name_the_extra(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "pandas", None)          # what `import pandas` does where it is not installed
    with pytest.raises(ModuleNotFoundError, match=r"install it with: pip install 'flocktrack\[analysis\]'$"):
        flocktrack.load(tmp_path)
    assert main(["export", str(tmp_path), "--out", str(tmp_path / "tables")]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith("error: export: this needs pandas") and "flocktrack[analysis]" in err[0]


def test_import_flocktrack_and_its_command_line_do_not_import_pandas():
    code = ("import sys, flocktrack, flocktrack.cli; flocktrack.cli.parser(); "
            "assert callable(flocktrack.load); print(sorted(m for m in ('pandas', 'pyarrow') if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]"
