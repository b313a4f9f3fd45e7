"""Report plots for benchmarks and training (PNG, matplotlib without a display)."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence


def _pyplot():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _finish(plt, fig, ax, path: str | Path, title: str, x_label: str, y_label: str) -> Path:
    """Label, grid and legend the axes, write the PNG and free the figure."""
    ax.set(title=title, xlabel=x_label, ylabel=y_label)
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def pareto_front(points: Sequence[tuple[float, float]], higher_is_better: bool = True) -> list[int]:
    """Indices of the points no other point beats on both cost (x, lower is better) and
    quality (y); sorted by x."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], -points[i][1] if higher_is_better else points[i][1]))
    front, best = [], None
    for i in order:
        y = points[i][1]
        if best is None or (y > best if higher_is_better else y < best):
            front.append(i)
            best = y
    return front


def pareto_plot(rows: Sequence[dict[str, Any]], x: str, y: str, label: str, path: str | Path, *,
                title: str, x_label: str, y_label: str, higher_is_better: bool = True,
                log_x: bool = False) -> Path:
    """Scatter of rows (cost `x` vs quality `y`), each point labelled, the Pareto front
    drawn as a step line. Returns the PNG path."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)
    pts = [(float(r[x]), float(r[y])) for r in rows]
    ax.scatter([p[0] for p in pts], [p[1] for p in pts], s=28, zorder=3)
    for r, (px, py) in zip(rows, pts):
        ax.annotate(str(r[label]), (px, py), textcoords="offset points", xytext=(4, 4), fontsize=7)
    front = pareto_front(pts, higher_is_better)
    ax.step([pts[i][0] for i in front], [pts[i][1] for i in front], where="post", color="tab:red",
            lw=1, label="Pareto front")
    if log_x:
        ax.set_xscale("log")
    return _finish(plt, fig, ax, path, title, x_label, y_label)


def curve_plot(series: dict[str, tuple[Sequence[float], Sequence[float]]], path: str | Path, *, title: str,
               x_label: str, y_label: str) -> Path:
    """Line plot of named (x, y) series, e.g. accuracy vs training step. Returns the PNG path."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)
    for name, (xs, ys) in series.items():
        ax.plot(list(xs), list(ys), label=name, lw=1.2)
    return _finish(plt, fig, ax, path, title, x_label, y_label)


def markdown_table(rows: Sequence[dict[str, Any]], columns: Sequence[str]) -> str:
    """Rows as a Markdown table (floats to 4 significant digits)."""
    def fmt(v: Any) -> str:
        return f"{v:.4g}" if isinstance(v, float) else str(v)
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(fmt(r.get(c, "")) for c in columns) + " |" for r in rows]
    return "\n".join(lines)
