"""Success and bits of trained teams under channel noise (docs/noise.md).

Evaluates every run of each run folder under each noise setting (``sparsecomm.channel.noise``:
packet erasure, symmetric bit flips, which make a packet fail its CRC-32, Gilbert-Elliott
bursts; the receiver uses the null message for a lost packet, or its last good one), with the
same evaluation episodes for every setting, and writes the rows and a figure.

    python benchmarks/noise_table.py --runs runs/noise_clean runs/noise_erasure20 \
        --out docs/results/noise/table.json
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import tyro  # noqa: E402

from sparsecomm.channel import NoiseConfig  # noqa: E402
from sparsecomm.experiment import evaluate_runs  # noqa: E402
from sparsecomm.provenance import hardware  # noqa: E402
from sparsecomm.runfolder import learner_for, load_run  # noqa: E402

SETTINGS = {
    "clean": (NoiseConfig(), "none"),
    "erasure 0.1": (NoiseConfig(erasure=0.1, on_drop="null"), "none"),
    "erasure 0.2": (NoiseConfig(erasure=0.2, on_drop="null"), "none"),
    "erasure 0.4": (NoiseConfig(erasure=0.4, on_drop="null"), "none"),
    "erasure 0.2, last": (NoiseConfig(erasure=0.2, on_drop="last"), "none"),
    "erasure 0.4, last": (NoiseConfig(erasure=0.4, on_drop="last"), "none"),
    "erasure 0.1, last": (NoiseConfig(erasure=0.1, on_drop="last"), "none"),
    "flip 1e-3": (NoiseConfig(flip=1e-3, on_drop="null"), "none"),
    "flip 1e-2": (NoiseConfig(flip=1e-2, on_drop="null"), "none"),
    "flip 5e-2": (NoiseConfig(flip=5e-2, on_drop="null"), "none"),
    "burst": (NoiseConfig(burst=True, on_drop="null"), "none"),
    "clean, hamming": (NoiseConfig(), "hamming74"),
    "flip 1e-2, hamming": (NoiseConfig(flip=1e-2, on_drop="null"), "hamming74"),
    "flip 5e-2, hamming": (NoiseConfig(flip=5e-2, on_drop="null"), "hamming74"),
    "flip 1e-3, last": (NoiseConfig(flip=1e-3), "none"),
    "flip 1e-2, last": (NoiseConfig(flip=1e-2), "none"),
    "flip 5e-2, last": (NoiseConfig(flip=5e-2), "none"),
    "burst, last": (NoiseConfig(burst=True), "none"),
    "clean, permuted": (NoiseConfig(), "permuted"),
    "flip 1e-3, permuted": (NoiseConfig(flip=1e-3), "permuted"),
    "flip 1e-2, permuted": (NoiseConfig(flip=1e-2), "permuted"),
    "flip 5e-2, permuted": (NoiseConfig(flip=5e-2), "permuted"),
    "asymmetric, permuted": (NoiseConfig(flip_01=0.1, flip_10=0.05), "permuted"),
    "burst, permuted": (NoiseConfig(burst=True), "permuted"),
    "delay 1": (NoiseConfig(delay=1), "none"),
    "delay 3": (NoiseConfig(delay=3), "none"),
}
"""The noise settings, by name, with the framing the senders use: ``none``, the run's packets
(CRC-32; the paper's code for a run trained on the permuted channel), ``hamming74``
(``ChannelConfig.ecc``) or ``permuted`` (``ChannelConfig.code``: no CRC, flips corrupt
symbols, ``sparsecomm.channel.permuted``). The receiver uses the null message for a lost packet
unless the name says ``last`` or ``permuted`` (there: its last good message, the default).
Bursts: the defaults, 1/11 of steps bad, flips 0.1 there; ``asymmetric``: AAAI 2020's flips,
0 -> 1 at 0.1 and 1 -> 0 at 0.05; ``delay d``: every message arrives d steps late."""


def framed(channel, noise: NoiseConfig, framing: str):
    """``channel`` under ``noise`` with the framing of a setting (see ``SETTINGS``)."""
    if framing == "permuted":
        return dataclasses.replace(channel, noise=noise, code="permuted", code_file="", ecc="none")
    code = "paper" if channel.code == "permuted" else channel.code
    return dataclasses.replace(channel, noise=noise, ecc=framing, code=code)


@dataclasses.dataclass
class Args:
    runs: tuple[Path, ...]
    """Run folders (every run of each is evaluated)."""
    settings: tuple[str, ...] = (
        "clean",
        "erasure 0.1",
        "erasure 0.2",
        "erasure 0.4",
        "erasure 0.2, last",
        "flip 1e-3",
        "flip 1e-2",
        "flip 5e-2",
        "burst",
    )
    """Names of the noise settings to evaluate (keys of ``SETTINGS``)."""
    episodes: int = 500
    """Evaluation episodes per run and setting."""
    out: Path | None = None
    """JSON file for the rows (the figure goes beside it, ``.png``)."""


def main(args: Args) -> list[dict]:
    rows = []
    for folder in args.runs:
        config, _, runs, actor = load_run(folder)
        trained = config.channel.noise
        for name in args.settings:
            noise, ecc = SETTINGS[name]
            channel = framed(config.channel, noise, ecc)
            learner = learner_for(dataclasses.replace(config, channel=channel))
            result = evaluate_runs(learner, runs, actor, args.episodes)
            for group, m in result["by_group"].items():
                row = {
                    "run": str(folder),
                    "trained_under": dataclasses.asdict(trained),
                    "group": group,
                    "setting": name,
                    "ecc": "none" if ecc == "permuted" else ecc,
                    "framing": ecc,
                    "seeds": sum(1 for r in runs if r.group == group),
                    **{k: m[k] for k in m},
                }
                rows.append(row)
                s = m["episode/success_rate"]
                print(
                    f"{folder} {group:>10} | {name:>17}: success {s['mean']:.3f} "
                    f"[{s['ci_low']:.3f}, {s['ci_high']:.3f}] length "
                    f"{m['episode/episode_length']['mean']:.1f} "
                    f"bits {m['channel/bits_per_step']['mean']:.1f} "
                    f"lost/step {m.get('channel/packets_lost_per_step', {'mean': 0.0})['mean']:.2f}"
                )
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        payload = {"args": {**dataclasses.asdict(args)}, "rows": rows, "hardware": hardware()}
        args.out.write_text(json.dumps(payload, indent=2, default=str))
        figure(rows, args.out.with_suffix(".png"))
    return rows


def figure(rows: list[dict], path: Path) -> None:
    """Success (mean and 95% CI) per noise setting, one line per trained team and group."""
    settings = list(dict.fromkeys(r["setting"] for r in rows))
    fig, ax = plt.subplots(figsize=(9, 4))
    lines = dict.fromkeys((r["run"], r["group"]) for r in rows)
    for i, (run, group) in enumerate(lines):
        sel = {r["setting"]: r for r in rows if (r["run"], r["group"]) == (run, group)}
        x = [j + 0.08 * (i - len(lines) / 2) for j, s in enumerate(settings) if s in sel]
        s = [sel[name]["episode/success_rate"] for name in settings if name in sel]
        mean = [v["mean"] for v in s]
        err = [[v["mean"] - v["ci_low"] for v in s], [v["ci_high"] - v["mean"] for v in s]]
        ax.errorbar(x, mean, yerr=err, fmt="o-", capsize=3, label=f"{Path(run).name} {group}")
    ax.set_xticks(range(len(settings)), settings, rotation=30, ha="right")
    ax.set_ylabel("success rate (95% CI over seeds)")
    ax.set_ylim(0, 1.05)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    main(tyro.cli(Args))
