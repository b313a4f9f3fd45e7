"""The slip models shipped in fv_algos/weights (`slip_<name>.pt`, its record `slip_<name>.json` beside it):
their names, as the slip detector's `model` param and every `--model` of the command line take them, and the
checkpoint a name stands for. Imports nothing heavy: the commands' helps list the names (`model_help`)."""
from __future__ import annotations

from pathlib import Path

WEIGHTS_DIR = Path(__file__).resolve().parent.parent / "fv_algos" / "weights"

# shipped names that stand for another shipped model: `gelsight` is the GelSight Mini model that
# `fv eval --trials` and the slip detector both mean by it, the whole-grasp trial model
ALIASES = {"gelsight": "gelsight_trial"}


def shipped_models() -> list[str]:
    """The shipped model names, aliases included, sorted."""
    return sorted([*(p.stem.removeprefix("slip_") for p in WEIGHTS_DIR.glob("slip_*.pt")), *ALIASES])


def model_help() -> str:
    """What a `--model` help says it takes: the shipped names (from the weights folder) or a checkpoint path."""
    return f"shipped model name ({', '.join(shipped_models())}) or checkpoint path"


def model_path(name: str) -> Path:
    """Checkpoint path of a shipped model name (or an ``ALIASES`` key), or the path itself;
    FileNotFoundError naming the shipped models."""
    shipped = WEIGHTS_DIR / f"slip_{ALIASES.get(name, name)}.pt"
    if shipped.is_file():
        return shipped
    path = Path(name).expanduser()  # a shell leaves the ~ of model:=~/m.pt as it is
    if path.is_file():
        return path
    raise FileNotFoundError(f"model {name!r} is neither a shipped model ({shipped_models()}) nor a checkpoint file")
