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


@pytest.mark.parametrize("argv, message", [
    (["bench", "bus", "--rate", "0"], "--rate: 0 is not a finite number > 0"),  # a traceback, then a hang
    (["bench", "bus", "--frames", "0"], "--frames"),                          # "error: p50"
    (["bench", "bus", "--rate", "nan", "--json"], "--rate: nan is not a finite number > 0"),  # NaN in the JSON
    (["bench", "pipeline", "--duration", "0"], "--duration: 0 is not a finite number > 0"),  # "success", no data
    (["bench", "pipeline", "--warmup", "-1"], "--warmup: -1 is not a finite number >= 0"),
    (["bench", "soak", "--minutes", "nan"], "--minutes: nan is not a finite number > 0"),
    (["bench", "bag", "--duration", "inf"], "--duration: inf is not a finite number > 0"),  # OverflowError
    (["eval", "--data", "d.npz", "--out", "r", "--repeats", "0"], "--repeats"),  # said so after training
    (["train", "--data", "d.npz", "--out", "r", "--export", "adir"], "--export: adir must end in .pt"),  # same
    (["eval", "--trials", "t", "--model", "gelsight", "--online", "--plot", "p.txt"], "--plot: p.txt must end in .png"),
    (["sim", "--scene", "s.yaml", "--out", "o", "--preview", "p.txt"], "--preview: p.txt must end in .png"),
    (["dataset", "sim", "--out", "x.txt"], "--out: x.txt must end in .npz"),  # written to x.txt.npz
    (["view", "--bag", "b", "--out", "o.png", "--at", "nan"], "--at: nan is not a finite number >= 0"),
    (["real", "train", "--trials", "t", "--out", "m1.json"], "--out: m1.json must end in .pt"),  # the record
    (["real", "train", "--trials", "t", "--out", "m.pt", "--lr", "inf"], "--lr: inf is not a finite number > 0"),
    (["real", "train", "--trials", "t", "--out", "m.pt", "--cv-report", "missing.json"],  # after training, the
     "--cv-report: missing.json: not an `fv real cv --out` report"),                       # model left without record
    (["view", "--bag", "b", "--out", "o.mp4", "--fps", "nan"], "--fps: nan is not a finite number >= 0"),
    (["sim", "--frames", "2", "--seed", "-1"], "--seed: -1 is not a seed from 0 to 2**63 - 1"),  # numpy's words
    (["train", "--data", "d.npz", "--out", "r", "--seed", "1" + "0" * 20], "--seed: 1000"),  # after loading
    (["real", "cv", "--trials", "t", "--seed", "x"], "--seed: 'x' is not a whole number"),
    (["train", "--data", "d.npz", "--out", "r", "--threads", "0"], "--threads: 0 is not >= 1"),  # torch's words
])
def test_numbers_and_outputs_that_cannot_work_are_refused_before_any_work(argv: list[str], message: str,
                                                                          tmp_path: Path, capsys,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2 and message in capsys.readouterr().err


def test_a_data_set_larger_than_the_free_memory_is_refused_before_simulating(tmp_path: Path, capsys) -> None:
    """`fv dataset sim --sequences 100000000000` simulated until the memory ran out."""
    assert main(["dataset", "sim", "--sequences", "100000000000", "--out", str(tmp_path / "d.npz")]) == 2
    assert "--sequences 100000000000 of 15 frames need up to 32400000.0 GB" in capsys.readouterr().err
    assert main(["dataset", "sim", "--grasps", "--frames", "100", "--fps", "5", "--out", str(tmp_path / "g.npz")]) == 2
    assert "--frames 100: every grasp is shorter at 5 fps" in capsys.readouterr().err  # said after simulating them


@pytest.mark.parametrize("argv, message", [
    (["bench", "judge", "--layers", "70"], "--layers 70: at most 12"),  # OverflowError
    (["bench", "soak", "--minutes", "0.1", "--sample", "100"], "needs two samples at least"),  # checks "passed"
    (["bench", "bag", "--keep", "."], "--keep . exists: give a new folder"),  # waited 15 s for the recorder
    (["bench", "bag", "--duration", "0.01"], "--duration 0.01 s at --fps 60.0 publishes no frame"),  # "no topic"
    (["bench", "slip", "--threads", "1,0"], "--threads 1,0: every thread count must be >= 1"),  # "warmup"
    (["bench", "bus", "--throughput-frames", "1"], "a throughput needs 2 frames at least"),  # 0.0 frames/s
])
def test_benchmarks_that_would_measure_nothing_are_refused(argv: list[str], message: str, capsys) -> None:
    assert main(argv) == 2 and message in capsys.readouterr().err


def test_a_simulated_sequence_is_not_written_among_an_earlier_ones_frames(tmp_path: Path, capsys) -> None:
    """`fv sim --frames 3 --out seq` into a folder of 60 earlier frames left frames 3-59 beside the
    new 3-frame truth.npz."""
    (tmp_path / "seq").mkdir()
    (tmp_path / "seq" / "frame_0059.png").write_bytes(b"")
    assert main(["sim", "--frames", "3", "--out", str(tmp_path / "seq")]) == 2
    assert "holds files already" in capsys.readouterr().err
    assert main(["sim", "--frames", "2", "--out", str(tmp_path / "new")]) == 0
    assert (tmp_path / "new").is_dir()
