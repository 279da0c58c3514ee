"""Grouped metric names and the learner registry: files with the flat names of before still
read with the grouped names, and only the registry spells the learner kinds."""

import ast
import json
from pathlib import Path

import pytest

from sparsecomm import learners
from sparsecomm.configs import ILConfig, RLConfig
from sparsecomm.metric_names import GROUPS, alias, aliased_results, written
from sparsecomm.pipelines.claims import summarize_runs
from sparsecomm.runfolder import _config, kind_of
from sparsecomm.stats import curves, read_csv
from sparsecomm.sweep import differences

ROOT = Path(__file__).resolve().parent.parent / "sparsecomm"


def test_every_metric_has_one_group_and_the_alias_adds_it():
    keys = [k for ks in GROUPS.values() for k in ks]
    assert len(keys) == len(set(keys))
    assert written("success_rate") == alias("success_rate") == "episode/success_rate"
    assert alias("actor_grad_norm") == "loss/actor_grad_norm"
    assert alias("episode/success_rate") == "episode/success_rate"  # already grouped
    assert alias("env_steps") == "env_steps"  # a run's coordinate, no metric
    with pytest.raises(KeyError, match="no group"):
        written("not_a_metric")


def test_a_run_folder_with_the_flat_names_reads_with_the_grouped_names(tmp_path):
    # metrics.csv and results.json as written before the groups
    (tmp_path / "metrics.csv").write_text(
        "seed,lam,budget,update,env_steps,episodes,success_rate,bits_per_step,price\n"
        "0,0.0,,1,48,4,0.25,12.5,0\n0,0.0,,2,96,8,0.5,10,0\n"
    )
    data = read_csv(tmp_path / "metrics.csv")
    assert {"episode/success_rate", "channel/bits_per_step", "budget/price", "seed"} <= set(data)
    ((steps, vals),) = curves(data, "success_rate").values()  # a flat name asked reads too
    assert list(steps) == [48, 96] and vals.tolist() == [[0.25, 0.5]]
    old = {"runs": [{"seed": 0, "lam": 0.0, "success_rate": 0.5, "episode_length": 30.0}]}
    old["by_group"] = {"0": {"success_rate": {"mean": 0.5}}}
    new = aliased_results(json.loads(json.dumps(old)))
    assert new["runs"][0]["episode/success_rate"] == 0.5
    assert new["by_group"]["0"]["episode/success_rate"] == {"mean": 0.5}
    assert summarize_runs(old["runs"])[0.0]["episode/episode_length"]["mean"] == 30.0


def test_the_registry_names_each_kind_and_reads_the_old_names():
    assert kind_of(RLConfig()) == learners.RL.name == "rl"
    assert kind_of(ILConfig()) == learners.IMITATION.name == "imitation"
    assert learners.named("train") is learners.RL
    assert learners.named("imitate") is learners.IMITATION
    assert learners.RL.algo_of(RLConfig(algo="ppo")) == "ppo" and "ppo" in learners.RL.algos
    assert learners.IMITATION.algo_of(ILConfig()) == "dagger"
    assert learners.IMITATION.algo_of(ILConfig(beta_end=1.0)) == "bc"
    for kind in learners.KINDS.values():
        assert (ROOT.parent / kind.docs).exists()
    # a run folder written before the kinds had names recorded the command; it reads and resumes
    assert type(_config({"kind": "imitate", "config": {}}, Path("x"))) is ILConfig
    old = {"kind": "train", "config": {}, "seeds": 1, "lams": [0.0]}
    new = {"kind": "rl", "config": {}, "seeds": 1, "lams": [0.0], "budgets": [None]}
    assert differences(old, {**new, "start_from": ""}) == []
    assert differences({**old, "kind": "imitate"}, {**new, "start_from": ""}) != []


NOT_KINDS = {
    "sparsecomm.configs": "configs.PRESETS is keyed by command; configs sits below the registry",
    "sparsecomm.pipelines": "the pipelines' parts are named after their folders",
}
"""Modules whose strings ``rl``/``imitation`` name something else than a learner kind."""


def test_only_the_registry_spells_the_learner_kinds():
    spelled = {n for kind in learners.KINDS.values() for n in (kind.name, kind.command)}
    found = []
    for path in sorted(ROOT.rglob("*.py")):
        module = ".".join(("sparsecomm", *path.relative_to(ROOT).with_suffix("").parts))
        if module == "sparsecomm.learners" or module.startswith(tuple(NOT_KINDS)):
            continue
        tree = ast.parse(path.read_text())
        docs = {id(n.value) for n in ast.walk(tree) if isinstance(n, ast.Expr)}
        found += [
            f"{module}:{node.lineno}: {node.value!r}"
            for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and node.value in spelled and id(node) not in docs
        ]
    assert found == [], "\n".join(found)
