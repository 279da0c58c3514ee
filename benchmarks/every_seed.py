"""Every seed of a sweep, and how fast the sweep's mean got there: a run folder's per-seed table.

Reads the run folder that ``sparsecomm train --seeds N ...`` wrote (``run.json``,
``metrics.csv``, ``wall.csv``, ``results.json``) and, with ``--reference``, a second folder of the
same seeds under another learner (run back to back on the same machine), and writes

    {"command": str, "hardware": str, "per_seed": [{"seed": int, "success": float,
     "episode_length": float, "update_090": int | null}], "wall_s_to_095": float | null,
     "reference": {the same fields for the reference folder}}

``success`` and ``episode_length`` are each seed's own evaluation (``results.json``,
``--eval-episodes`` episodes); ``update_090`` the first update at which the seed's training
success, as a moving average of ``--window`` updates, passed 0.90; ``wall_s_to_095`` the
wall-clock (``wall.csv``, compiling included, at the end of the chunk holding that update) at
which the mean of the seeds' training success, averaged the same way, first passed 0.95.

    python benchmarks/every_seed.py runs/every_seed_gae095 --reference runs/every_seed_paper_fast \\
        --command "sparsecomm train --preset paper_fast ..." --out every_seed.json
"""

from __future__ import annotations

import argparse
import json
import platform
from pathlib import Path

import numpy as np

from sparsecomm.stats import first_pass, read_csv


def seed_curves(folder: Path) -> np.ndarray:
    """(updates, seeds) training success per update from ``metrics.csv`` (one lambda, one
    budget: a seed sweep)."""
    data = read_csv(folder / "metrics.csv")
    seeds, seed_index = np.unique(data["seed"].astype(int), return_inverse=True)
    updates, update_index = np.unique(data["update"].astype(int), return_inverse=True)
    curves = np.full((len(updates), len(seeds)), np.nan)
    curves[update_index, seed_index] = data["episode/success_rate"]
    return curves


def wall_at(folder: Path, update: int) -> float:
    """The wall-clock at the end of the chunk holding 1-based ``update`` (``wall.csv``)."""
    wall = read_csv(folder / "wall.csv")
    later = np.nonzero(wall["update"] >= update)[0]
    if len(later) == 0:
        raise ValueError(f"{folder}/wall.csv ends before update {update}")
    return float(wall["wall_s"][later[0]])


def table(folder: Path, window: int) -> dict:
    """The per-seed rows and the mean's wall-clock to 0.95 of one run folder."""
    base = json.loads((folder / "run.json").read_text())["config"]["seed"]
    curves = seed_curves(folder)
    runs = json.loads((folder / "results.json").read_text())["runs"]
    per_seed = []
    for run in runs:
        passed = first_pass(curves[:, run["seed"]], 0.90, window)
        per_seed.append(
            {
                "seed": base + run["seed"],
                "success": run["episode/success_rate"],
                "episode_length": run["episode/episode_length"],
                "update_090": None if passed is None else passed + 1,
            }
        )
    mean = first_pass(curves.mean(1), 0.95, window)
    return {
        "folder": str(folder),
        "per_seed": per_seed,
        "wall_s_to_095": None if mean is None else wall_at(folder, mean + 1),
        "update_095": None if mean is None else mean + 1,
    }


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("folder", type=Path, help="the candidate's run folder")
    p.add_argument("--reference", type=Path, default=None, help="the reference's run folder")
    p.add_argument("--command", default="", help="the commands that made the folders")
    p.add_argument("--hardware", default=f"{platform.processor() or platform.machine()}, CPU")
    p.add_argument("--window", type=int, default=10, help="updates in the moving averages")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    result = {"command": args.command, "hardware": args.hardware, **table(args.folder, args.window)}
    result["reference"] = None if args.reference is None else table(args.reference, args.window)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    for name, t in (("candidate", result), ("reference", result["reference"])):
        if t is None:
            continue
        ok = sum(s["success"] >= 0.90 for s in t["per_seed"])
        mean = np.mean([s["success"] for s in t["per_seed"]])
        print(
            f"{name}: {ok} of {len(t['per_seed'])} seeds >= 0.90, mean success {mean:.3f}, "
            f"mean past 0.95 at update {t['update_095']}, {t['wall_s_to_095']} s"
        )


if __name__ == "__main__":
    main()
