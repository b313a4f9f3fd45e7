"""`fv bench judge`: one row per network shape, with the sizes the shapes imply."""
from __future__ import annotations

import json

import pytest

from nodes.cli import main


def test_bench_judge_times_every_shape(capsys) -> None:
    assert main(["bench", "judge", "--layers", "1", "2", "--members", "1", "3", "--hidden", "4", "--frames", "20",
                 "--repeats", "1", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [(r["layers"], r["members"]) for r in rows] == [(1, 1), (1, 3), (2, 1), (2, 3)]
    assert [r["memory_frames"] for r in rows] == [5, 5, 13, 13]  # 2 * radius + 1, radius 2 and 2 + 4
    assert rows[1]["params"] == 3 * rows[0]["params"] and rows[3]["params"] == 3 * rows[2]["params"]
    assert all(r["ms_per_frame"] > 0 for r in rows) and rows[0]["ratio_to_first"] == 1.0


def test_bench_judge_refuses_an_empty_ensemble(capsys) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["bench", "judge", "--members", "0"])
    assert exit_.value.code == 2 and "argument --members: 0 is not" in capsys.readouterr().err
