"""A sweep's seconds per update on one CPU device against one device per core, side by side.

Runs the same ``sparsecomm train`` command once per device count (``JAX_NUM_CPU_DEVICES``), one
after the other on the same machine, and reads the time per update from each run folder's
``wall.csv`` between the end of the first chunk (compilation included there) and the end of
the last; ``results.json`` says how many devices the sweep used (``sharding.sweep_devices``
takes as many as divide its runs). Everything after ``--`` goes to ``sparsecomm train``:

    python benchmarks/host_devices.py --updates 150 -- --preset paper_fast \
        --config.channel.link-gate --config.channel.on-silence hold \
        --config.channel.news-margin 0.1 --config.budget.relief-floor 0.5 \
        --budgets None 32 --seeds 5 --config.seed 2000      # 10 runs
    python benchmarks/host_devices.py --updates 60 -- --preset paper_fast --seeds 5  # 5 runs
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import tyro

from sparsecomm.stats import read_csv
from sparsecomm.sweep import WALL_CSV


@dataclasses.dataclass
class Args:
    devices: tuple[int, ...] = (1, 2)
    """CPU device counts to compare (``JAX_NUM_CPU_DEVICES``), run in this order."""
    updates: int = 60
    """Updates per run (``--config.num-updates``); the first chunk is left out of the timing."""
    chunk: int = 10
    """Updates per compiled call (``--chunk``)."""
    out: Path | None = None
    """Write the figures here as JSON (default: print only)."""


def seconds_per_update(run: Path) -> float:
    """Seconds per update after the first chunk, from ``run/wall.csv`` (update, seconds)."""
    wall = read_csv(run / WALL_CSV)
    updates, seconds = wall["update"], wall["wall_s"]
    if len(updates) < 2:
        raise SystemExit(f"--updates must span at least two chunks, got one in {run}")
    return float((seconds[-1] - seconds[0]) / (updates[-1] - updates[0]))


def main(args: Args, train_args: list[str]) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for count in args.devices:
            run = Path(tmp) / f"devices{count}"
            cmd = [sys.executable, "-m", "sparsecomm.cli", "train", *train_args]
            cmd += ["--config.num-updates", str(args.updates), "--chunk", str(args.chunk)]
            cmd += ["--out", str(run), "--eval-episodes", "16", "--no-gif", "--no-progress"]
            cmd += ["--no-tensorboard"]
            subprocess.run(cmd, env={**env, "JAX_NUM_CPU_DEVICES": str(count)}, check=True)
            used = json.loads((run / "results.json").read_text())["devices"]
            per_update = round(seconds_per_update(run), 4)
            rows.append({"cpu_devices": count, "sweep_devices": used, "s_per_update": per_update})
            print(f"{count} CPU device(s), the sweep on {used}: {per_update} s per update")
    result = {"train_args": train_args, "updates": args.updates, "chunk": args.chunk, "rows": rows}
    if args.out is not None:
        args.out.write_text(json.dumps(result, indent=1) + "\n")
    return result


if __name__ == "__main__":
    argv = sys.argv[1:]
    split = argv.index("--") if "--" in argv else len(argv)
    main(tyro.cli(Args, args=argv[:split]), argv[split + 1 :])
