"""Environment-only throughput of the JAX navigation task.

``batch_size`` environments are stepped in parallel (vmap) for ``num_steps`` steps (lax.scan)
with uniformly random actions, in one jitted call. Compilation is excluded (one warm-up call);
the figure is env steps per second (one env step = all K agents acting once) over ``repeats``
timed calls, best and median.

    python benchmarks/env_throughput.py --batch-size 4096 --num-steps 256 --repeats 5
"""

from __future__ import annotations

import dataclasses
import os
import platform
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from sparsecomm.envs import (
    NavConfig,
    NavigationEnv,
    center_actions,
    oracle_actions,
    run_policy_episodes,
)


@dataclasses.dataclass
class Args:
    batch_size: int = 4096
    """Number of parallel environments (vmap)."""
    num_steps: int = 256
    """Steps per timed call (lax.scan); the default is one full episode length."""
    repeats: int = 5
    """Timed calls (after one untimed warm-up call that compiles)."""
    seed: int = 0
    """PRNG seed."""
    scripted_episodes: int = 0
    """If > 0, also run this many episodes of the oracle and the centre policy (seed ``seed``)
    and print their success rate, episode length and group reward."""


def make_runner(env: NavigationEnv, batch_size: int, num_steps: int):
    k = env.num_agents

    def one_env(key):
        key_reset, key_steps = jax.random.split(key)
        _, state = env.reset(key_reset)

        def body(carry, step_key):
            state, total = carry
            key_act, key_env = jax.random.split(step_key)
            actions = jax.random.randint(key_act, (k,), 0, env.num_actions)
            obs, state, rewards, dones, info = env.step(key_env, state, actions)
            # Consume the outputs so nothing is dead-code eliminated.
            total = total + rewards.sum() + obs.sum() + dones.sum() + info["success"]
            return (state, total), None

        (state, total), _ = jax.lax.scan(
            body, (state, jnp.zeros((), jnp.float32)), jax.random.split(key_steps, num_steps)
        )
        return total

    @jax.jit
    def run(key):
        return jax.vmap(one_env)(jax.random.split(key, batch_size)).sum()

    return run


def main(args: Args) -> dict[str, float]:
    env = NavigationEnv(NavConfig())
    run = make_runner(env, args.batch_size, args.num_steps)
    key = jax.random.PRNGKey(args.seed)
    t0 = time.perf_counter()
    jax.block_until_ready(run(key))
    compile_s = time.perf_counter() - t0
    times = []
    for i in range(args.repeats):
        key_i = jax.random.fold_in(key, i + 1)
        t0 = time.perf_counter()
        jax.block_until_ready(run(key_i))
        times.append(time.perf_counter() - t0)
    steps = args.batch_size * args.num_steps
    best, median = steps / min(times), steps / statistics.median(times)
    print(f"jax {jax.__version__}, backend {jax.default_backend()}, devices {jax.devices()}")
    print(f"python {platform.python_version()}, cpus visible {os.cpu_count()}")
    print(
        f"batch {args.batch_size} x {args.num_steps} steps = {steps} env steps per call; "
        f"compile+first call {compile_s:.2f} s"
    )
    print("call times (s): " + ", ".join(f"{t:.3f}" for t in times))
    print(
        f"env steps/s: best {best:,.0f}, median {median:,.0f} "
        f"(agent steps/s: best {best * env.num_agents:,.0f})"
    )
    result = {"best": best, "median": median, "compile_s": compile_s}
    if args.scripted_episodes > 0:
        for name, policy in (("oracle", oracle_actions), ("center", center_actions)):
            stats = run_policy_episodes(key, env.config, policy, args.scripted_episodes)
            success, length, reward = (np.asarray(x) for x in stats)
            print(
                f"{name}: {args.scripted_episodes} episodes (seed {args.seed}): success "
                f"{success.mean():.1%}, episode length mean {length.mean():.1f} median "
                f"{np.median(length):.0f} max {length.max()}, group reward mean {reward.mean():.0f}"
            )
            result[f"{name}_success"] = float(success.mean())
            result[f"{name}_length"] = float(length.mean())
    return result


if __name__ == "__main__":
    import tyro

    main(tyro.cli(Args))
