"""Bits per step of trained teams under every code, beside the entropy of their messages.

For each run (``FOLDER`` or ``FOLDER:INDEX``), plays ``--fit-episodes`` episodes, fits a code to
their symbols (``sparsecomm.channel.fitted``), then plays ``--eval-episodes`` other episodes and
counts, per step for the whole team: the paper's payload bits, the wire bits of the old framing
(logged and as packets), of the silence-free paper framing, of the fitted code (with and without
its CRC-32, and its codeword bits alone), and the plug-in entropies (``sparsecomm.codestats``).
With constriction installed, also the same model coded by its range coder per packet.

    python benchmarks/code_table.py --runs runs/codes_rl_small:0 runs/codes_rl_small:2 \
        --groups 1 2 3 5 --out docs/results/codes/table.json
    python benchmarks/code_table.py --show docs/results/codes/*.json   # the table again
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import jax
import tyro

from sparsecomm.channel.fitted import fit
from sparsecomm.codestats import FIT_SEED_OFFSET, link_symbols, measure
from sparsecomm.configs import ILConfig
from sparsecomm.provenance import hardware
from sparsecomm.runfolder import load_run

EVAL_OFFSET = 3_000_017


@dataclasses.dataclass
class Args:
    runs: tuple[str, ...]
    """Run folders, each ``FOLDER`` or ``FOLDER:INDEX`` (which run of the sweep; default 0)."""
    fit_episodes: int = 2000
    """Episodes the code is fitted to."""
    eval_episodes: int = 2000
    """Held-out episodes the bits and entropies are measured on."""
    groups: tuple[int, ...] = (5,)
    """Presence-group sizes to fit (the table's fitted columns use the first)."""
    seed: int = 0
    """Offset of the fitting and evaluation episodes' seeds."""
    out: Path | None = None
    """JSON file for the rows."""


COLUMNS = [
    ("payload", "payload (paper)"),
    ("wire_old_packet", "old packets (CRC-16)"),
    ("wire_silence_free", "silence-free (paper code)"),
    ("wire_fitted", "fitted, wire"),
    ("wire_fitted_no_crc", "fitted, no CRC"),
    ("fitted_code_bits", "fitted codewords"),
    ("fitted_model_bits", "fitted model, ideal"),
    ("fitted_range_coder_bits", "range coder (constriction)"),
    ("H_element", "H per element"),
    ("H_element_given_prev", "H given prev"),
]


def table(rows: list[dict]) -> str:
    """The markdown table of docs/channel.md: bits per step of the whole team."""
    lines = [
        "| team | " + " | ".join(label for _, label in COLUMNS) + " | codewords / H given prev "
        "| wire / H given prev |",
        "|---|" + "---|" * (len(COLUMNS) + 2),
    ]
    for r in rows:
        s = r["per_step"]
        what = "λ 0" if r["budget"] is None else f"budget {r['budget']:g}"
        if r["budget"] is None and r["lam"]:
            what = f"λ {r['lam']:g}"
        team = f"{r['learner']} K={r['agents']}, {what} (g={r['group']}, {r['run']})"
        cells = [f"{s[n]:.1f}" if n in s else "-" for n, _ in COLUMNS]
        h = max(s["H_element_given_prev"], 1e-9)
        ratios = f"{s['fitted_code_bits'] / h:.2f} | {s['wire_fitted'] / h:.2f}"
        lines.append(f"| {team} | " + " | ".join(cells) + f" | {ratios} |")
    return "\n".join(lines)


def main(args: Args) -> list[dict]:
    rows = []
    for spec in args.runs:
        folder, _, index = spec.partition(":")
        index = int(index or 0)
        config, trainer, runs, actor = load_run(Path(folder))
        params = jax.tree.map(lambda x, i=index: x[i], actor)
        start = time.perf_counter()
        fit_key = jax.random.key(config.seed + FIT_SEED_OFFSET + args.seed)
        eval_key = jax.random.key(config.seed + EVAL_OFFSET + args.seed)
        links, valid = link_symbols(trainer, config.channel, params, fit_key, args.fit_episodes)
        held, held_valid = link_symbols(
            trainer, config.channel, params, eval_key, args.eval_episodes
        )
        k = config.env.num_agents
        per_step = k * (k - 1)
        run = runs[index]
        for group in args.groups:
            code = fit(links, valid, levels=config.channel.levels, group=group)
            m = measure(code, held, held_valid, config.channel.levels)
            row = {
                "run": spec,
                "learner": "imitation" if isinstance(config, ILConfig) else "rl",
                "agents": k,
                "lam": run.lam,
                "budget": run.budget,
                "seed": run.seed,
                "group": group,
                "per_step": {
                    name: m[name] * per_step
                    for name in m
                    if not name.startswith(("H_distinct", "H_link_steps", "silent"))
                },
                "silent_links": m["silent_links"],
                "distinct_messages": m["H_distinct_messages"],
                "link_steps": m["H_link_steps"],
                "seconds": time.perf_counter() - start,
            }
            rows.append(row)
            print(json.dumps(row))
    print()
    print(table(rows))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        result = {"args": {**dataclasses.asdict(args), "out": str(args.out)}, "rows": rows}
        result["hardware"] = hardware()
        args.out.write_text(json.dumps(result, indent=2))
    return rows


if __name__ == "__main__":
    import sys

    if sys.argv[1:2] == ["--show"]:  # print the table of JSON files written by --out
        rows = [r for f in sys.argv[2:] for r in json.loads(Path(f).read_text())["rows"]]
        print(table(rows))
    else:
        main(tyro.cli(Args))
