"""Output paths checked before a job runs, and errors from the file system reported without a traceback."""
from __future__ import annotations

import argparse
import logging
from pathlib import Path

import pytest

from nodes.arg_types import output_file, output_folder
from nodes.cli import main


def test_output_paths_that_cannot_be_written_are_refused(tmp_path: Path) -> None:
    (tmp_path / "a_file").write_text("")
    assert output_file(str(tmp_path / "new" / "deeper" / "m.pt")) == tmp_path / "new" / "deeper" / "m.pt"
    assert output_folder(str(tmp_path / "new")) == tmp_path / "new"
    assert output_folder(str(tmp_path)) == tmp_path
    assert not (tmp_path / "new").exists()  # checked, not created
    for check, text, message in [
        (output_file, tmp_path / "a_file" / "m.pt", f"{tmp_path / 'a_file'} is a file, not a folder"),
        (output_file, tmp_path, f"{tmp_path} is a folder, not a file"),
        (output_folder, tmp_path / "a_file", f"{tmp_path / 'a_file'} is a file, not a folder"),
        (output_folder, tmp_path / "a_file" / "run" / "x", f"{tmp_path / 'a_file'} is a file, not a folder"),
    ]:
        with pytest.raises(argparse.ArgumentTypeError, match=message):
            check(str(text))


def test_a_bad_output_is_refused_before_the_job_runs(tmp_path: Path, capsys) -> None:
    (tmp_path / "a_file").write_text("")
    with pytest.raises(SystemExit) as exit_info:
        main(["dataset", "sim", "--out", str(tmp_path / "a_file" / "d.npz"), "--sequences", "2"])
    assert exit_info.value.code == 2
    assert f"argument --out: {tmp_path / 'a_file'} is a file, not a folder" in capsys.readouterr().err


def test_a_file_system_error_in_a_command_is_one_line_naming_it(monkeypatch: pytest.MonkeyPatch, capsys,
                                                                 caplog: pytest.LogCaptureFixture) -> None:
    import nodes.sim_commands

    def full_disk(args: argparse.Namespace) -> int:
        raise OSError(28, "No space left on device", "/data/run/frame_00007.png")
    monkeypatch.setattr(nodes.sim_commands, "_sim", full_disk)
    with caplog.at_level(logging.DEBUG, logger="fv"):
        assert main(["sim", "--frames", "2"]) == 2
    assert capsys.readouterr().err == "fv sim: error: [Errno 28] No space left on device: '/data/run/frame_00007.png'\n"
    assert caplog.records[-1].exc_info[0] is OSError  # the traceback goes to the debug log (fv -v)
