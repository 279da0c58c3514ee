"""Where the time of one training update goes: a ``jax.profiler`` trace, summed by kind of op.

Compiles the default RL update (``rl.make_train``), traces one call with ``jax.profiler.trace``
(a Perfetto trace is written too, open it at ui.perfetto.dev), and sums the durations of the
executed XLA ops. Each op is named back to the JAX code that made it through the compiled HLO's
``op_name`` metadata, and put in one class: actor / critic matmuls, random draws (threefry),
zero-filled buffers (the scan's stacked residuals and outputs), copies and transposes,
stacking per step (dynamic-update-slice), other element-wise work. Op time is summed over the
runtime's threads, so it exceeds wall-clock time when both cores work.

    python benchmarks/profile_update.py --num-envs 256 --trace-dir /tmp/sparsecomm-trace
    python benchmarks/profile_update.py --naive     # the naive REINFORCE step of naive_step.py
"""

from __future__ import annotations

import argparse
import collections
import glob
import gzip
import json
import re
import time

import jax

from sparsecomm.configs import RLConfig
from sparsecomm.envs.navigation import NavConfig
from sparsecomm.rl import make_train

CLASSES = (
    ("matmul: critic", lambda kind, src: kind == "dot" and "Critic" in src),
    ("matmul: actors", lambda kind, src: kind == "dot"),
    ("random draws (threefry)", lambda kind, src: re.search(r"threefry|_uniform|_gumbel", src)),
    ("zero-filled buffers", lambda kind, src: kind == "broadcast"),
    ("copies and transposes", lambda kind, src: kind in ("copy", "transpose")),
    ("stacking per step (dynamic-update-slice)", lambda kind, src: kind == "dus"),
    ("other element-wise", lambda kind, src: True),
)


def op_kind(name: str) -> str:
    """Coarse kind of a compiled HLO instruction from its name."""
    if name.startswith(("dot", "ynn_fusion")) or "convolution" in name:
        return "dot"  # ynn_fusion: a dot lowered to YNNPACK
    if name.startswith("wrapped_broadcast"):
        return "broadcast"
    if name.startswith("copy") or name.startswith("transpose"):
        return "copy"
    if "dynamic-update-slice" in name:
        return "dus"
    return "other"


def op_sources(hlo_text: str) -> dict[str, str]:
    """HLO instruction name -> the JAX ``op_name`` that produced it."""
    pattern = re.compile(r"^\s*%?(\S+) = .*?op_name=\"([^\"]*)\"", re.M)
    return {m.group(1): m.group(2) for m in pattern.finditer(hlo_text)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--num-envs", type=int, default=256)
    p.add_argument("--agents", type=int, default=3)
    p.add_argument("--max-steps", type=int, default=256)
    p.add_argument("--trace-dir", default="/tmp/sparsecomm-trace")
    p.add_argument("--top", type=int, default=12, help="also list the N most costly ops")
    p.add_argument("--naive", action="store_true", help="profile naive_step.py's step instead")
    a = p.parse_args()

    cfg = RLConfig(env=NavConfig(num_agents=a.agents, max_steps=a.max_steps), num_envs=a.num_envs)
    if a.naive:
        from naive_step import make_naive  # beside this script

        init, naive_update = make_naive(cfg)
        state = init(jax.random.key(0))
        update = jax.jit(naive_update).lower(state).compile()
    else:
        tr = make_train(cfg)
        state = jax.jit(tr.init)(jax.random.key(0), 0.0)
        update = jax.jit(lambda s: tr.update_chunk(s, 1)[0]).lower(state).compile()
    sources = op_sources(update.as_text())
    jax.block_until_ready(update(state))  # warm up
    t0 = time.perf_counter()
    jax.block_until_ready(update(state))
    wall = time.perf_counter() - t0
    with jax.profiler.trace(a.trace_dir, create_perfetto_trace=True):
        t0 = time.perf_counter()
        jax.block_until_ready(update(state))
        traced_wall = time.perf_counter() - t0

    path = sorted(glob.glob(f"{a.trace_dir}/**/*.trace.json.gz", recursive=True))[-1]
    events = json.load(gzip.open(path))["traceEvents"]
    per_op, per_class = collections.Counter(), collections.Counter()
    threads = set()
    for e in events:
        name = e.get("name", "")
        # Leaf XLA ops only: no Python frames, no executor wrappers, no loop containers.
        if e.get("ph") != "X" or name.startswith("$") or "Thunk" in name:
            continue
        if name.startswith("while") or name.startswith("end: "):
            continue
        per_op[name] += e["dur"] / 1e6
        threads.add(e["tid"])
        kind, src = op_kind(name), sources.get(name, "")
        label = next(label for label, test in CLASSES if test(kind, src))
        per_class[label] += e["dur"] / 1e6
    total = sum(per_class.values())
    steps = a.num_envs * a.max_steps
    print(
        f"{'naive step' if a.naive else 'sparsecomm update'}: {a.num_envs} episodes x "
        f"{a.max_steps} steps, K = {a.agents}: "
        f"{wall:.2f} s wall ({steps / wall:,.0f} env steps/s), {traced_wall:.2f} s traced; "
        f"op time {total:.2f} s on {len(threads)} threads"
    )
    for label, _ in CLASSES:
        print(f"  {label:42s} {per_class[label]:6.3f} s  {100 * per_class[label] / total:5.1f}%")
    print(f"top {a.top} ops:")
    for name, secs in per_op.most_common(a.top):
        print(f"  {secs:6.3f} s  {name:32s} {sources.get(name, '')[-90:]}")
    print(f"trace: {path} (jax {jax.__version__}, {jax.devices()[0].platform})")


if __name__ == "__main__":
    main()
