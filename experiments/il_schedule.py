"""Behaviour cloning vs DAgger with the oracle expert, one seed on CPU (docs/imitation.md).

    python experiments/il_schedule.py 0.0 100 12   # DAgger: beta 1 -> 0 over 100 updates
    python experiments/il_schedule.py 1.0 100 12   # behaviour cloning: beta = 1 throughout

Arguments: beta_end, beta_decay_updates, number of 25-update chunks. Prints the learners' own
success (256 evaluation episodes, learners drive) after each chunk.
"""

import sys
import time

import jax

from sparsecomm.configs import ILConfig
from sparsecomm.imitation import make_imitate

beta_end, decay, chunks = float(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
im = make_imitate(ILConfig(num_envs=32, beta_end=beta_end, beta_decay_updates=decay))
state = im.init(jax.random.key(0), 0.0)
evaluate = jax.jit(lambda p: im.evaluate(p, jax.random.key(99), 256))
step = jax.jit(im.update_chunk, static_argnums=1)
t0 = time.time()
for i in range(chunks):
    state, m = step(state, 25)
    e = evaluate(state.params["actor"])
    print(
        f"{(i + 1) * 25:4d} updates {time.time() - t0:5.0f}s "
        f"imitation loss {float(m['imitation_loss'][-5:].mean()):.3f} "
        f"beta {float(m['beta'][-1]):.2f} success {float(e['success_rate']):.3f} "
        f"length {float(e['episode_length']):.1f} bits {float(e['bits_per_step']):.1f}",
        flush=True,
    )
