"""The paper's task with bit budgets, RL and imitation, in one command (docs/paper-task.md).

    sparsecomm paper-task                      # every part, then the summary
    sparsecomm paper-task --parts rl           # one part (and the summary of what is there)

Each part is a run folder under ``out``, trained as one vmapped program by
:func:`sparsecomm.experiment.train`, so a part that dies resumes from its checkpoint and a
finished part is only re-evaluated:

============= ==================================================================================
``rl``        RL (``rl``: the ``paper_fast`` preset, hard gate, links silent but on news), lambda 0
              and the ``budgets``
``il_oracle`` imitation of the oracle (``il``: the ``paper`` preset, the ``rl`` part's links),
              lambda 0 and the budgets
``il_rl``     imitation of the ``rl`` part's best lambda-0 team (the paper's expert: highest
              success, ties to the shortest episodes), lambda 0 and the budgets
``rl_lams``   RL at the paper's lambdas (0.01, 0.005, 0.001): claim 4 at the paper's points
``il_lams``   imitation of the oracle at the paper's lambdas (Table I): claim 5 at its points
============= ==================================================================================

Then, from every part found in ``out``, it writes to ``results``:

- ``summary.json``: one row per (part, budget, lambda) group over its seeds, rows of the wire
  form of :mod:`sparsecomm.pipelines.rows` (``learner``, ``algo``, ``expert``, ``budget``, ``lam``,
  ``seeds``, ``success``, ``episode_length``, ``payload_bits``, ``wire_bits`` as ``[mean, lo,
  hi]`` with 95% BCa CIs over seeds, ``env_steps_to_095``, ``wall_s_to_095``, ``per_seed``,
  ...) with a ``series`` naming the expert of imitation of the RL team;
- ``frontier.png``: success against payload and wire bits
  (:func:`sparsecomm.pipelines.frontier.plot`);
- ``claims.json``: claims 4 and 5 at budget-matched points and at the paper's lambdas, and the
  task's targets (budget 32, stretch 16, met within 10% at >= 95% of lambda 0's success with
  episodes at most 1.25x its length: :func:`sparsecomm.pipelines.frontier.targets`), judged on
  sampled actions (the convention of training, ``sparsecomm eval`` and deployed agents); with
  ``greedy``, ``targets_greedy`` judges the same targets on the teams' most probable actions.

With ``greedy`` every part's runs are evaluated a second time taking their most probable
actions (``sparsecomm eval --greedy``, written to ``eval_greedy.json`` in the part's folder),
and each row carries those figures under ``greedy``.

docs/paper-task.md has the figures and the wall-clock of each part on 2 CPU cores.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from sparsecomm.channel import ChannelConfig
from sparsecomm.configs import PRESETS, ILConfig, RLConfig, check_budget_fits
from sparsecomm.experiment import evaluate_runs
from sparsecomm.jsonfile import read_json, write_json
from sparsecomm.pipelines import claims, frontier
from sparsecomm.pipelines import rows as rowlib
from sparsecomm.pipelines.plan import (
    IL_LAMS,
    RL_LAMS,
    Part,
    Sweep,
    check_expert_unset,
    check_parts,
    expert_index,
)
from sparsecomm.pipelines.runner import SweepOptions, part_rows, run_parts
from sparsecomm.runfolder import at_least, check_output, load_run, read_config

PLAN = (
    Part("rl", "rl"),
    Part("il_oracle", "imitation"),
    Part("il_rl", "imitation", "RL team", needs="rl"),
    Part("rl_lams", "rl"),
    Part("il_lams", "imitation"),
)
"""Every part, in the order they run (``il_rl`` needs ``rl``), with its rows' learner and series
(each series is judged against its own lambda 0)."""
PARTS = tuple(p.name for p in PLAN)
"""Every part's name, in the order they run."""
NEWS = ChannelConfig(link_gate=True, on_silence="hold", news_margin=0.1)
"""The ``rl`` part's channel: a gate per link that news also opens (a gap of 0.1 between what a
sender would say and what its recipient holds), a silent link held by its recipient; payload
prices and budgets as the paper's. The ``silent`` preset's links (docs/wire.md) with the paper's
frame check; chosen on tuning seeds 1000-1001 (docs/paper-task.md, links that fall silent, RL)."""
_FAST_RL = PRESETS["paper_fast"]["train"]
_IL = dataclasses.replace(PRESETS["paper"]["imitate"], channel=NEWS)
GOALS, MAX_LENGTH_RATIO = (32.0, 16.0), 1.25
"""The paper task's targets: budget 32, then the stretch 16, with episodes at most 1.25x lambda
0's."""
GREEDY = "eval_greedy.json"
"""A part's evaluation with the most probable actions, beside its ``results.json``."""


@dataclasses.dataclass
class PaperTask:
    """The paper's task with bit budgets, RL and imitation: trains, evaluates, summarises."""

    out: Path = Path("runs/paper")
    """Folder of the parts' run folders (one sub-folder per part; a folder this user can write,
    or a path where one can be created: checked before any part runs)."""
    results: Path = Path("docs/results/paper")
    """Folder of ``summary.json``, ``frontier.png`` and ``claims.json`` (checked as ``out``)."""
    parts: tuple[str, ...] = PARTS
    """Parts to run (any of ``PARTS``); the summary covers every part found in ``out``.
    ``il_rl`` needs ``rl``: with it, or with a finished ``rl`` part in ``out``."""
    seeds: int = 5
    """Seeds per group (seed s of every part uses ``key(config.seed + s)``). ours: 5, the least the
    targets ask for (docs/paper-task.md); the 95% CIs cover at most 94% at n = 5
    (``stats.bootstrap_ci``)."""
    budgets: tuple[float, ...] = (64.0, 32.0, 16.0)
    """Payload budgets (bits per step for the team) of ``rl``, ``il_oracle`` and ``il_rl``, each
    beside a lambda-0 reference in the same program. ours: the paper task's (docs/paper-task.md)."""
    rl: RLConfig = dataclasses.replace(
        _FAST_RL,
        channel=NEWS,
        budget=dataclasses.replace(_FAST_RL.budget, relief_floor=0.5),
        ent_coef=0.003,
        num_updates=6000,
    )
    """The RL learner: the ``paper_fast`` preset (a2c, 16 episodes per update, the learning
    rate falling from 1e-3 to 1e-4 over 2000 updates, the hard gate) with links that fall
    silent but speak on news (:data:`NEWS`), the controller's relief bounded at half the last
    good price (``relief_floor`` 0.5, as the ``silent`` preset's), an entropy bonus of 0.003
    and 6000 updates (96,000 episodes per run). ours: the preset's learner tuned on seeds
    1000-1003, the update count and the bonus from the verdicts on seeds 0-19
    (docs/paper-task.md)."""
    il: ILConfig = _IL
    """The imitation learner: the ``paper`` preset (the settings with which docs/budget.md
    confirmed the bounded relief on this task) with the ``rl`` part's links that fall silent but
    speak on news (:data:`NEWS`); its expert is set by the part (``--il.expert*`` refused).
    ours: tuned on seeds 1000-1001 (docs/paper-task.md, imitation of the oracle with links that
    fall silent: budgets 32 and 16 met there, where the plain channel stayed near 45 bits on the
    verdict seeds)."""
    eval_episodes: int = 500
    """Final-evaluation episodes per run."""
    greedy: bool = True
    """Also evaluate every run on ``eval_episodes`` episodes taking its most probable actions
    (``GREEDY`` in each part's folder; a row's ``greedy``, claims.json's ``targets_greedy``).
    The verdicts stay on sampled actions. ours: on, since a team that acts on its most probable
    actions is the other way to deploy it (docs/paper-task.md)."""
    chunk: int = 25
    """Updates per compiled call (the logging and wall-clock granularity)."""
    checkpoint_every: int = 2
    """Save a checkpoint every this many chunks (and at the end)."""
    resume: bool = True
    """Continue parts from their checkpoints in ``out``."""
    gif: bool = False
    """Render ``team.gif`` of the first run of each part."""
    progress: bool = True
    """Show progress bars."""

    def __post_init__(self):
        at_least(self, seeds=1, eval_episodes=1, chunk=1, checkpoint_every=1)
        bad = [p for p in self.parts if p not in PARTS]
        if bad or not self.parts:
            raise ValueError(f"PaperTask.parts must be a non-empty subset of {PARTS}, got {bad}")
        if not self.budgets:
            raise ValueError("PaperTask.budgets must hold at least one budget, got ()")
        for config in (self.rl, self.il):  # refused now, not after the parts before it ran
            check_budget_fits(config, self.budgets, "budgets", owner="PaperTask")
        check_expert_unset(self, _IL)
        check_parts(self, PLAN)
        check_output(self, "results", folder=True)


def build_part(args: PaperTask, part: str) -> Sweep:
    """The sweep of one part."""
    rl, il = args.rl, args.il
    budgets = (None, *args.budgets)
    if part == "rl":
        return Sweep(rl, budgets=budgets)
    if part == "rl_lams":
        return Sweep(rl, lams=tuple(x for x in RL_LAMS if x > 0))
    if part == "il_oracle":
        return Sweep(dataclasses.replace(il, expert="oracle"), budgets=budgets)
    if part == "il_lams":
        lams = tuple(x for x in IL_LAMS if x > 0)
        return Sweep(dataclasses.replace(il, expert="oracle"), lams=lams)
    if part == "il_rl":
        folder = args.out / "rl"
        expert = dict(expert_checkpoint=str(folder), expert_index=expert_index(folder))
        return Sweep(dataclasses.replace(il, expert="checkpoint", **expert), budgets=budgets)
    raise ValueError(f"part must be one of {PARTS}, got {part!r}")


def sweep_options(args: PaperTask) -> SweepOptions:
    """What every part's sweep shares."""
    return SweepOptions(
        seeds=args.seeds,
        eval_episodes=args.eval_episodes,
        chunk=args.chunk,
        checkpoint_every=args.checkpoint_every,
        resume=args.resume,
        tensorboard=False,
        gif=args.gif,
        progress=args.progress,
    )


def evaluate_greedy(folder: Path, episodes: int) -> Path:
    """Evaluate every run of a part's folder with its most probable actions into ``GREEDY``."""
    _, trainer, runs, actor = load_run(folder)
    write_json(folder / GREEDY, evaluate_runs(trainer, runs, actor, episodes, greedy=True))
    return folder / GREEDY


def with_greedy(rows: list[dict], folder: Path, task: str, learner: str) -> list[dict]:
    """``rows`` with a ``greedy`` field from ``folder``'s ``GREEDY`` evaluation (the metrics of
    :data:`sparsecomm.pipelines.rows.WIRE_COLUMNS` as ``[mean, lo, hi]`` and ``per_seed``),
    matched by group; unchanged when the folder has none."""
    results = read_json(folder / GREEDY)
    if results is None:
        return rows
    # rows, not read_rows: the training curves were read for ``rows`` already
    greedy = rowlib.rows(results, learner, config=read_config(folder), task=task)
    found = {(r["budget"], r["lam"]): r for r in greedy}
    names = (*rowlib.WIRE_COLUMNS, "per_seed")
    out = []
    for row in rows:
        g = found.get((row["budget"], row["lam"]))
        out.append(row if g is None else row | {"greedy": {k: g[k] for k in names}})
    return out


def greedy_table(table: list[dict]) -> list[dict]:
    """The rows that have greedy figures, with those figures in place of the sampled ones."""
    return [r | r["greedy"] for r in table if "greedy" in r]


def summarise(args: PaperTask) -> list[dict]:
    """``summary.json``, ``frontier.png`` and ``claims.json`` from the parts found in ``out``,
    and the rows an earlier ``summary.json`` in ``results`` holds of parts not found there (a
    part run earlier, whose run folder is gone, keeps its rows)."""
    found = {}
    for part in PLAN:
        rows = part_rows([part], args.out, task="paper").get(part.name)
        if rows is None:
            continue
        rows = with_greedy(rows, args.out / part.name, "paper", part.learner)
        found[part.name] = [row | {"part": part.name, "series": part.series} for row in rows]
    if not found:
        return []
    earlier = [rowlib.from_json(r) for r in read_json(args.results / "summary.json") or []]
    kept = [r for r in earlier if r.get("part") in PARTS and r["part"] not in found]
    for row in kept:
        found.setdefault(row["part"], []).append(row)
    table = [row for part in PARTS for row in found.get(part, [])]
    args.results.mkdir(parents=True, exist_ok=True)
    write_json(args.results / "summary.json", table)
    frontier.plot(table, args.results / "frontier.png", "The paper's task: bit budgets")
    earlier_claims = read_json(args.results / "claims.json") or {}
    verdicts = {
        "budget_matched": frontier.budget_claims(table),
        "lambdas": lambda_claims(table, earlier_claims.get("lambdas", [])),
        "targets": frontier.targets(table, GOALS, max_length_ratio=MAX_LENGTH_RATIO),
        "targets_greedy": frontier.targets(
            greedy_table(table), GOALS, max_length_ratio=MAX_LENGTH_RATIO
        ),
    }
    write_json(args.results / "claims.json", verdicts)
    return table


LAMBDA_CLAIMS = (
    ("rl_lams", "rl", "rl", claims.claim_sparse_rl),
    ("il_lams", "il_oracle", "imitation", claims.claim_imitation),
)
"""Each ``*_lams`` part, the part whose lambda-0 runs are its reference, the learner's name in
:mod:`sparsecomm.pipelines.claims` and the claim that judges them (4 and 5)."""


def lambda_claims(table: list[dict], earlier: list[dict]) -> list[dict]:
    """Claims 4 and 5 at the paper's lambdas: each ``*_lams`` part's runs with its series'
    lambda-0 runs (the ``rl`` / ``il_oracle`` row without a budget), read from the rows'
    per-seed figures (:func:`sparsecomm.pipelines.rows.seed_runs`), so that a verdict survives
    its run folders. A claim whose rows lack them (rows written before rows carried per-seed
    figures) keeps its ``earlier`` verdict."""
    found = []
    for part, ref, name, claim in LAMBDA_CLAIMS:
        lams = [r for r in table if r["part"] == part]
        zero = [r for r in table if r["part"] == ref and r["budget"] is None]
        runs = [run for r in lams + zero for run in rowlib.seed_runs(r)]
        if not lams or not zero or len(runs) < sum(r["seeds"] for r in lams + zero):
            found += [c for c in earlier if c.get("part") == part]
            continue
        c = claim({name: claims.summarize_runs(runs)})
        verdict = {"claim": c.number, "label": c.text, "held": c.held, "evidence": c.evidence}
        found.append({"part": part, **verdict})
    return found


def paper_task(args: PaperTask) -> list[dict]:
    """Run the parts in order, then write the summary; returns its rows."""

    def greedy(part: str, _record: dict, _seconds: float) -> None:
        if args.greedy:
            evaluate_greedy(args.out / part, args.eval_episodes)
        else:  # an earlier one would describe parameters this part may have left
            (args.out / part / GREEDY).unlink(missing_ok=True)

    header = "paper-task: part {part} -> {folder}"
    build = lambda part: build_part(args, part)  # noqa: E731
    run_parts(PLAN, args.parts, build, sweep_options(args), args.out, header, greedy)
    table = summarise(args)
    for r in table:
        name = "λ 0" if r["budget"] is None else f"budget {r['budget']:g}"
        if r["budget"] is None and r["lam"] > 0:
            name = f"λ {r['lam']:g}"
        reach = r["env_steps_to_095"]
        print(
            f"{r['part']:9s} {name:10s} success {r['success'][0]:.3f} "
            f"[{r['success'][1]:.3f}, {r['success'][2]:.3f}], length {r['episode_length'][0]:.1f}, "
            f"payload {r['payload_bits'][0]:.1f}, wire {r['wire_bits'][0]:.1f}, "
            f"0.95 at {'-' if reach is None else f'{reach / 1e6:.1f}M env steps'}"
            + (
                f"; greedy: success {r['greedy']['success'][0]:.3f}, "
                f"length {r['greedy']['episode_length'][0]:.1f}"
                if "greedy" in r
                else ""
            )
        )
    if table:
        print(f"summary -> {args.results / 'summary.json'}, frontier.png, claims.json")
    return table
