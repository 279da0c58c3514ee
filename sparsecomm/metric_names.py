"""The names metrics are written under: ``group/name``, one group per concern.

The learners and the evaluation compute their metrics under flat keys (``success_rate``,
``bits_per_step``, ...: ``rollout.episode_metrics``, the losses, ``budget.log``); those keys
stay flat inside the library, where the budget controller, the channel's ``counted_metric``
and the compiled updates read them. Every file a run writes names each metric
``GROUP/key``, the group taken from :data:`GROUPS` (defined here once): the per-update
``metrics.csv``, the TensorBoard tags and ``results.json`` (and ``eval.json``). Readers see
the written names: files written before the groups (flat names) are read through
:func:`alias`, so an old run folder reads as a new one.

The groups:

- ``episode/``: how the team did (per episode, the paper's units);
- ``channel/``: what the channel carried (bits per step, speakers, datagrams, losses, links);
- ``budget/``: the price of a bit and the controller's target;
- ``loss/``: the objective's terms, the imitation agreement, PPO's ratio statistics and the
  gradient norms;
- ``schedule/``: the schedules an update follows (imitation's ``beta``).
"""

from __future__ import annotations

GROUPS: dict[str, tuple[str, ...]] = {
    "episode": ("group_reward", "episode_length", "success_rate"),
    "channel": (
        "bits_per_step",
        "wire_bits_per_step",
        "speaking_fraction",
        "datagrams_per_step",
        "datagram_bits_per_step",
        "packets_lost_per_step",
        "links_per_step",
    ),
    "budget": ("price", "bit_target", "penalty_weight"),
    "loss": (
        "loss",
        "penalty",
        "policy_loss",
        "value_loss",
        "entropy",
        "imitation_loss",
        "expert_agreement",
        "clip_fraction",
        "approx_kl",
        "nonfinite",
    ),
    "schedule": ("beta",),
}
"""Every metric key a learner or the evaluation logs, by group. Units: rewards in the paper's
units per episode, lengths in steps, rates and fractions in [0, 1], bits per step of the whole
team; ``price`` and ``penalty_weight`` in lambda's units per bit; ``nonfinite`` counts the
non-finite values of an update. Gradient norms (``<part>_grad_norm``, one per parameter part)
are in ``loss``."""

GRAD_NORM = "_grad_norm"
"""The ending of a gradient norm's key (``actor_grad_norm``, ``critic_grad_norm``): group
``loss``."""

GROUP_OF: dict[str, str] = {key: group for group, keys in GROUPS.items() for key in keys}
"""The group of each metric key of :data:`GROUPS`."""


def group_of(key: str) -> str | None:
    """The group of the flat metric key ``key``, or None if it is no metric's."""
    if key.endswith(GRAD_NORM):
        return "loss"
    return GROUP_OF.get(key)


def written(key: str) -> str:
    """The name the flat metric key ``key`` is written under: ``group/key``. A key with no
    group is a ``KeyError`` naming it (every logged metric must have one, :data:`GROUPS`)."""
    group = group_of(key)
    if group is None:
        raise KeyError(f"metric {key!r} has no group in sparsecomm.metric_names.GROUPS")
    return f"{group}/{key}"


def alias(name: str) -> str:
    """The written name of ``name`` as a reader sees it: a flat metric key (files written
    before the groups) becomes ``group/key``; a grouped name, or a name that is no metric's
    (``seed``, ``lam``, ``update``, ``env_steps``, ...), stays as it is."""
    if "/" in name:
        return name
    group = group_of(name)
    return name if group is None else f"{group}/{name}"


def aliased(row: dict) -> dict:
    """``row`` with every key read through :func:`alias` (the values as they are)."""
    return {alias(k): v for k, v in row.items()}


def written_row(metrics: dict) -> dict:
    """``metrics`` (flat keys) with every key as :func:`written` names it."""
    return {written(k): v for k, v in metrics.items()}


def aliased_results(results: dict) -> dict:
    """A ``results.json`` or ``eval.json`` document with its metric names read through
    :func:`alias`: each run of ``runs`` and each group of ``by_group``."""
    out = dict(results)
    if "runs" in out:
        out["runs"] = [aliased(run) for run in out["runs"]]
    if "by_group" in out:
        out["by_group"] = {g: aliased(m) for g, m in out["by_group"].items()}
    return out
