"""sparsecomm's training update against a naive JAX step, side by side in one run.

The reference is what a user would write first: the same navigation task and the same actor
network (``sparsecomm.agents.Actor``, shared parameters with a one-hot agent id, GRU 64), the
dithered channel with one dither draw per step inside the time loop, plain REINFORCE on the
discounted return (no critic, no entropy, no bit penalty), one Adam step. sparsecomm's update
(``sparsecomm.rl.make_train``, default ``RLConfig``) does more: a centralised critic, GAE,
advantage standardisation, the entropy bonus, the bit penalty and its metrics, the per-link
shared-key dither. Both update ``--num-envs`` episodes of 256 steps per call; the calls are
alternated and the median of ``--repeats`` is reported, compile time excluded.

    python benchmarks/naive_step.py --num-envs 64 256            # CPU
    python benchmarks/naive_step.py --num-envs 64 --channel.prices wire --channel.link-gate
    python benchmarks/naive_step.py --num-envs 256 2560 10240    # GPU
"""

from __future__ import annotations

import dataclasses
import statistics
import time

import jax
import jax.numpy as jnp
import optax
import tyro

from sparsecomm import channel
from sparsecomm.configs import ChannelConfig, RLConfig
from sparsecomm.rl import make_train


@dataclasses.dataclass
class Args:
    num_envs: tuple[int, ...] = (64, 256)
    """Episodes per update (one row each)."""
    repeats: int = 5
    """Timed calls of each step, alternated."""
    seed: int = 0
    """PRNG seed of both."""
    channel: ChannelConfig = ChannelConfig()
    """sparsecomm's channel (the naive step keeps the default one, the common reference), e.g.
    ``--channel.prices wire --channel.link-gate --channel.on-silence hold`` for the price of
    speaking (docs/wire.md)."""


def make_naive(config: RLConfig):
    """``(init, update)`` of the naive REINFORCE step on the task and actor of ``config``."""
    learner = make_train(config)
    env, team, levels = learner.env, learner.team, config.channel.levels
    k, b, t_max = env.num_agents, config.num_envs, env.config.max_steps
    tx = optax.adam(config.lr)

    def loss(params, key):
        k_reset, k_steps = jax.random.split(key)
        obs, state = jax.vmap(env.reset)(jax.random.split(k_reset, b))
        msgs = jnp.zeros((b, k, (k - 1) * config.channel.num_elements))

        def step(loop, key_t):
            state, obs, msgs, h = loop
            k_act, k_dither, k_env = jax.random.split(key_t, 3)
            h, logits, z = team.act(params, h, obs, msgs)
            actions = jax.random.categorical(k_act, jax.lax.stop_gradient(logits))
            u = jax.random.uniform(k_dither, z.shape, minval=-0.5, maxval=0.5)
            _, z_hat = channel.quantize_dithered(z, u, levels)
            logp = jnp.take_along_axis(jax.nn.log_softmax(logits), actions[..., None], -1)
            valid = ~state.done
            obs, state, rewards, _, _ = jax.vmap(env.step)(
                jax.random.split(k_env, b), state, actions
            )
            return (state, obs, channel.deliver(z_hat), h), (logp[..., 0], rewards, valid)

        init = (state, obs, msgs, team.initial_carry(b))
        _, (logp, rewards, valid) = jax.lax.scan(step, init, jax.random.split(k_steps, t_max))
        rewards = rewards * config.reward_scale * valid[..., None]

        def discount(ret, r):
            ret = r + config.gamma * ret
            return ret, ret

        _, returns = jax.lax.scan(discount, jnp.zeros_like(rewards[0]), rewards, reverse=True)
        adv = jax.lax.stop_gradient(returns - returns.mean((0, 1)))
        return -(logp * adv * valid[..., None]).sum() / valid.sum()

    def init(key):
        params = team.init(key)["actor"]
        return params, tx.init(params), key

    def update(state):
        params, opt_state, key = state
        key, k_loss = jax.random.split(key)
        grads = jax.grad(loss)(params, k_loss)
        updates, opt_state = tx.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, key

    return init, update


def _time(fn, state, repeats: int) -> tuple[list[float], object]:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        state = jax.block_until_ready(fn(state))
        times.append(time.perf_counter() - t0)
    return times, state


def main(args: Args) -> list[dict]:
    rows = []
    for n in args.num_envs:
        config = RLConfig(num_envs=n)
        steps = n * config.env.max_steps
        naive_init, naive_update = make_naive(config)
        ours = make_train(dataclasses.replace(config, channel=args.channel))
        fns = {
            "naive": (jax.jit(naive_update), naive_init(jax.random.key(args.seed))),
            "sparsecomm": (jax.jit(ours.update), ours.init(jax.random.key(args.seed), 0.0)),
        }
        states, times = {}, {name: [] for name in fns}
        for name, (fn, state) in fns.items():  # compile and first call
            states[name] = jax.block_until_ready(fn(state))
            if name == "sparsecomm":
                states[name] = states[name][0]
        for _ in range(args.repeats):  # alternated, one call each
            for name, (fn, _) in fns.items():
                t, out = _time(fn, states[name], 1)
                states[name] = out[0] if name == "sparsecomm" else out
                times[name] += t
        rate = {name: steps / statistics.median(t) for name, t in times.items()}
        row = {"num_envs": n, **rate, "ratio": rate["sparsecomm"] / rate["naive"]}
        rows.append(row)
        print(
            f"{n:>6} episodes: naive {rate['naive']:,.0f} env steps/s, sparsecomm "
            f"{rate['sparsecomm']:,.0f} (ratio {row['ratio']:.2f}; median of {args.repeats}, "
            f"{jax.devices()[0].platform}, jax {jax.__version__})"
        )
    return rows


if __name__ == "__main__":
    main(tyro.cli(Args))
