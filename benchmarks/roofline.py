"""Roofline estimate for the training step: matmul FLOPs per env step vs measured matmul FLOP/s.

Counts the multiply-adds of the default networks (actors: 2 dense layers, a GRU and two heads
per agent; centralised critic MLP) per env step, forward and backward (backward = 2 x forward,
the usual count for dense layers), then measures this machine's FLOP/s on the same matmul
shapes the update runs (per-step: one matmul per layer for the whole batch of episodes and the
K agents, batched over agents), and on one large square matmul. The bound is
``FLOP/s / FLOPs per env step``: what the update could reach if it did nothing but these
matmuls at the measured rate.

A third, tighter bound times a *skeleton* of the update: the same matmuls in the same
``lax.scan`` over the episode (actors batched over agents, one tanh so the recurrence is not
linear, critic per step), differentiated with ``jax.grad``, and nothing else: no environment, no
channel, no random draws. Whatever the real update adds on top of it is the overhead that an
optimisation could remove; the skeleton's rate is what the update could reach without it.

    python benchmarks/roofline.py --num-envs 256
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax
import jax.numpy as jnp

from sparsecomm.configs import RLConfig
from sparsecomm.learner import make_team


def layer_shapes(cfg: RLConfig, env, team):
    """(fan_in, fan_out) of every matmul of one agent step, and of the critic per env step."""
    a = cfg.agent
    actor = [
        (team.in_dim, a.hidden),
        (a.hidden, a.hidden),
        (a.hidden, 3 * a.gru),  # GRU input side, three gates
        (a.gru, 3 * a.gru),  # GRU hidden side
        (a.gru, env.num_actions),
        (a.gru, (env.num_agents - 1) * cfg.channel.num_elements),
    ]
    critic = [(env.state_dim, a.critic_hidden), (a.critic_hidden, a.critic_hidden)]
    critic.append((a.critic_hidden, env.num_agents))
    return actor, critic


def flops_per_env_step(cfg: RLConfig) -> dict:
    env, team = make_team(cfg)
    actor, critic = layer_shapes(cfg, env, team)
    fwd_actor = 2 * env.num_agents * sum(i * o for i, o in actor)
    fwd_critic = 2 * sum(i * o for i, o in critic)
    return {"actor": 3 * fwd_actor, "critic": 3 * fwd_critic, "shapes": (actor, critic)}


def timed(fn, *args, repeats=20):
    fn = jax.jit(fn)
    jax.block_until_ready(fn(*args))
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def skeleton_seconds(cfg: RLConfig, shapes, num_envs: int, repeats: int = 5) -> float:
    """Median seconds of ``jax.grad`` of the update's matmuls alone, scanned over the episode."""
    actor, critic = shapes
    k, t_len, gru = cfg.env.num_agents, cfg.env.max_steps, cfg.agent.gru
    key = jax.random.key(0)
    aw = [
        0.1 * jax.random.normal(jax.random.fold_in(key, n), (k, i, o))
        for n, (i, o) in enumerate(actor)
    ]
    cw = [0.1 * jax.random.normal(jax.random.fold_in(key, 9 + n), s) for n, s in enumerate(critic)]
    xs = jax.random.normal(key, (t_len, k, num_envs, actor[0][0]))
    states = jax.random.normal(key, (t_len, num_envs, critic[0][0]))

    def loss(aw, cw):
        w1, w2, w_in, w_hid, w_act, w_msg = aw

        def mm(x, w):
            return jnp.einsum("kbi,kio->kbo", x, w)

        def step(h, x):
            gates_in, gates_hid = mm(mm(mm(x, w1), w2), w_in), mm(h, w_hid)
            h = jnp.tanh(gates_in[..., :gru] + gates_hid[..., :gru])
            return h, mm(h, w_act).sum() + mm(h, w_msg).sum()

        _, out = jax.lax.scan(step, jnp.zeros((k, num_envs, gru)), xs)

        def value(s):
            for w in cw:
                s = s @ w
            return s.sum()

        return out.sum() + jax.lax.map(value, states).sum()

    return timed(jax.grad(loss, argnums=(0, 1)), aw, cw, repeats=repeats)


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--num-envs", type=int, default=256)
    a = p.parse_args()
    cfg = RLConfig(num_envs=a.num_envs)
    f = flops_per_env_step(cfg)
    total = f["actor"] + f["critic"]
    print(f"FLOPs per env step (matmuls, fwd + bwd): actor {f['actor']:,} critic {f['critic']:,}")
    print(f"  total {total:,}")
    k = cfg.env.num_agents
    key = jax.random.key(0)
    actor, critic = f["shapes"]
    # One step's actor matmuls, batched over agents: (K, B, in) @ (K, in, out).
    flops = 0
    xs, ws = [], []
    for i, o in actor:
        xs.append(jax.random.normal(key, (k, a.num_envs, i)))
        ws.append(jax.random.normal(key, (k, i, o)))
        flops += 2 * k * a.num_envs * i * o

    def step_matmuls(xs, ws):
        return [jnp.einsum("kbi,kio->kbo", x, w) for x, w in zip(xs, ws, strict=True)]

    t_step = timed(step_matmuls, xs, ws, repeats=200)
    rate_step = flops / t_step
    n = 1024
    big = jax.random.normal(key, (n, n))
    rate_big = 2 * n**3 / timed(lambda x: x @ x, big)
    print(
        f"matmul FLOP/s, one step's actor shapes (batch {a.num_envs} x {k} agents): "
        f"{rate_step / 1e9:.1f} G ({t_step * 1e6:.0f} us per step)"
    )
    print(f"matmul FLOP/s, {n} x {n} square: {rate_big / 1e9:.1f} G")
    for name, rate in (("step shapes", rate_step), ("square", rate_big)):
        print(f"roofline at the {name} rate: {rate / total:,.0f} env steps/s")
    steps = a.num_envs * cfg.env.max_steps
    t_skel = skeleton_seconds(cfg, f["shapes"], a.num_envs)
    print(
        f"skeleton update (the matmuls alone, scanned and differentiated): {t_skel:.3f} s, "
        f"{total * steps / t_skel / 1e9:.1f} GFLOP/s, bound {steps / t_skel:,.0f} env steps/s"
    )
    print(
        f"on {jax.devices()[0].platform}, {jax.local_device_count()} device(s), "
        f"jax {jax.__version__}"
    )


if __name__ == "__main__":
    main()
