"""Report plots: the Pareto front is the set no other point beats; PNGs are written."""
from __future__ import annotations

from pathlib import Path

import cv2

from nodes.plots import curve_plot, markdown_table, pareto_front, pareto_plot


def test_pareto_front_keeps_only_undominated_points() -> None:
    points = [(1.0, 0.90), (2.0, 0.95), (3.0, 0.94), (0.5, 0.50), (2.5, 0.97)]
    assert pareto_front(points) == [3, 0, 1, 4]
    assert pareto_front([(1.0, 0.2), (2.0, 0.1)], higher_is_better=False) == [0, 1]


def test_plots_write_readable_pngs(tmp_path: Path) -> None:
    rows = [{"ms": 1.0, "acc": 0.9, "name": "fast"}, {"ms": 10.0, "acc": 0.97, "name": "paper"}]
    for path in (pareto_plot(rows, "ms", "acc", "name", tmp_path / "p.png", title="t", x_label="ms", y_label="acc"),
                 curve_plot({"train": ([0, 1, 2], [0.5, 0.8, 0.9])}, tmp_path / "c.png", title="t", x_label="step",
                            y_label="acc")):
        image = cv2.imread(str(path))
        assert image is not None and image.shape[0] > 100 and image.std() > 1.0


def test_markdown_table_formats_rows() -> None:
    table = markdown_table([{"a": 1, "b": 0.123456}], ["a", "b"])
    assert table.splitlines() == ["| a | b |", "|---|---|", "| 1 | 0.1235 |"]
