"""Fault injection: damage checkpoints and kill runs at random moments, then resume them.

Trains one tiny reference run to the end, then for each trial copies a half-finished run,
injects one fault and runs the resume command (a fresh process, as a user would), and sorts
the outcome:

- ``recovered``: exit 0 with the reference's parameters, bit for bit, and its metrics.csv;
- ``refused``: exit 2 with a one-line message naming the damaged file, no traceback;
- ``silently wrong``: exit 0 with other parameters or other logs (target: 0);
- ``hung``: no exit within the timeout (target: 0);
- ``crashed``: any other exit (a traceback: a bug).

Faults: a flipped byte or a truncation of ``state.msgpack`` or ``config.json``, a deleted part,
a deleted checkpoint folder, and SIGKILL of a training process at a random moment (one to
three times in a row) before the resume.

    python benchmarks/fault_injection.py --trials 24 --seed 0      # docs/reliability.md
"""

from __future__ import annotations

import argparse
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import jax
import numpy as np

from sparsecomm.runfolder import load_run

UPDATES = 16
ARGS = [
    "train",
    "--config.env.max-steps", "8",
    "--config.num-envs", "4",
    "--config.num-updates", str(UPDATES),
    "--chunk", "1",
    "--checkpoint-every", "2",
    "--seeds", "2",
    "--eval-episodes", "4",
    "--no-gif",
    "--no-progress",
]  # fmt: skip
FAULTS = (
    "flip state.msgpack",
    "flip config.json",
    "truncate state.msgpack",
    "truncate config.json",
    "delete state.msgpack",
    "delete config.json",
    "delete checkpoint",
    "kill -9",
)


def command(out: Path, updates: int = UPDATES) -> list[str]:
    args = [a if a != str(UPDATES) else str(updates) for a in ARGS]
    return [sys.executable, "-m", "sparsecomm.cli", *args, "--out", str(out)]


def env() -> dict:
    return {**os.environ, "JAX_PLATFORMS": "cpu"}


def params(out: Path):
    return [np.asarray(x) for x in jax.tree.leaves(load_run(out)[3])]


def inject(fault: str, out: Path, rng: random.Random) -> None:
    ckpt = out / "checkpoint"
    if fault == "delete checkpoint":
        shutil.rmtree(ckpt)
        return
    if fault == "kill -9":
        for _ in range(rng.randint(1, 3)):
            proc = subprocess.Popen(command(out), env=env(), stderr=subprocess.DEVNULL)
            time.sleep(rng.uniform(2.0, 25.0))  # compiling, training or saving
            proc.send_signal(signal.SIGKILL)
            proc.wait()
        return
    action, name = fault.split()
    path = ckpt / name
    data = bytearray(path.read_bytes())
    if action == "flip":
        i = rng.randrange(len(data))
        data[i] ^= 1 << rng.randrange(8)
        path.write_bytes(bytes(data))
    elif action == "truncate":
        path.write_bytes(bytes(data[: rng.randrange(len(data))]))
    else:
        path.unlink()


def trial(fault: str, half: Path, ref: Path, work: Path, rng, timeout: float) -> tuple[str, str]:
    out = work / "run"
    shutil.rmtree(out, ignore_errors=True)
    shutil.copytree(half, out)
    inject(fault, out, rng)
    try:
        done = subprocess.run(
            command(out), env=env(), capture_output=True, text=True, timeout=timeout
        )
    except subprocess.TimeoutExpired:
        return "hung", ""
    err = done.stderr.strip()
    if done.returncode == 2 and "Traceback" not in err:
        lines = [x for x in err.splitlines() if x.startswith("sparsecomm: error:")]
        return ("refused", lines[-1]) if lines else ("crashed", err[-300:])
    if done.returncode != 0:
        return "crashed", err[-300:]
    same = all(np.array_equal(a, b) for a, b in zip(params(ref), params(out), strict=True))
    same_logs = (ref / "metrics.csv").read_text() == (out / "metrics.csv").read_text()
    return ("recovered", "") if same and same_logs else ("silently wrong", "")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=24)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--timeout", type=float, default=600.0)
    args = parser.parse_args()
    rng = random.Random(args.seed)
    work = Path(tempfile.mkdtemp(prefix="faults-"))
    ref, half = work / "reference", work / "half"
    subprocess.run(command(ref), env=env(), check=True, capture_output=True)
    subprocess.run(command(half, UPDATES // 2), env=env(), check=True, capture_output=True)
    counts: Counter = Counter()
    for t in range(args.trials):
        fault = FAULTS[t % len(FAULTS)]
        t0 = time.time()
        outcome, message = trial(fault, half, ref, work, rng, args.timeout)
        counts[outcome] += 1
        print(f"{t:3d} {fault:24s} {outcome:15s} {time.time() - t0:5.0f}s {message}", flush=True)
    print("\n" + ", ".join(f"{k}: {counts[k]}" for k in (
        "recovered", "refused", "silently wrong", "hung", "crashed")))  # fmt: skip
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
