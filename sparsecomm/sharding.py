"""Scale-out with ``jax.sharding``: the runs of a sweep and the episodes of a run over devices.

A sweep is a batch of independent runs (seeds x lambdas), and every run's update plays a batch of
independent episodes. :func:`make_mesh` lays the devices out as a 2-D mesh ``(runs, episodes)``:
runs are split over the first axis, each run's episodes over the second, and a run's parameters
are replicated along it. :func:`place_runs` puts the batched training state on the mesh, and
:func:`split_episodes` (called by the rollout on its batch axis) tells XLA to partition the
episodes. XLA's SPMD partitioner then inserts the one collective this needs: the sum of each
run's gradients over its episode shards. Nothing else is exchanged, so the results equal a
single-device run up to float summation order.

Multi-host: start every process with ``jax.distributed.initialize()`` (the CLI's
``--distributed.*`` flags, :class:`Distributed`) and pass ``devices=jax.devices()`` (all hosts'
devices) to :func:`sparsecomm.sweep.run_sweep` in every process. The mesh then spans hosts;
:func:`place_runs` builds the global arrays from each process's copy, :func:`to_host` gathers
metrics and state to every process, and only process 0 writes logs, checkpoints and results
(tested with 2 CPU processes, ``tests/test_sharding.py``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from collections.abc import Sequence

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

RUNS = "runs"
"""Mesh axis over which the runs of a sweep are split."""
EPISODES = "episodes"
"""Mesh axis over which each run's parallel episodes are split."""


@dataclasses.dataclass
class Distributed:
    """Join a multi-process JAX cluster (``jax.distributed``) before anything runs.

    Every process runs the same command; the sweep's runs and episodes are then split over the
    devices of all processes, and process 0 alone writes files. Fields left unset are
    auto-detected by JAX on the clusters it knows (SLURM, Open MPI, Kubernetes...).
    """

    enabled: bool = False
    """Call ``jax.distributed.initialize`` (off: a single process)."""
    coordinator_address: str | None = None
    """``host:port`` of process 0's coordinator (default: ``JAX_COORDINATOR_ADDRESS`` or the
    cluster's)."""
    num_processes: int | None = None
    """Number of processes (default: the cluster's)."""
    process_id: int | None = None
    """This process's index in ``[0, num_processes)`` (default: the cluster's)."""

    def initialize(self) -> None:
        """Join the cluster (a no-op unless ``enabled``). CPU collectives go over gloo."""
        if not self.enabled:
            return
        n, i = self.num_processes, self.process_id
        if n is not None and n < 1:
            raise ValueError(f"distributed.num_processes must be >= 1, got {n}")
        if i is not None and n is not None and not 0 <= i < n:
            raise ValueError(f"distributed.process_id must be in [0, {n - 1}], got {i}")
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize(self.coordinator_address, n, i)


def is_primary() -> bool:
    """Whether this process writes the files (logs, checkpoints, results): process 0 under
    ``jax.distributed``, always with one process."""
    return jax.process_index() == 0


def make_mesh(num_runs: int, num_envs: int, devices: Sequence | None = None) -> Mesh | None:
    """A ``(runs, episodes)`` mesh over ``devices`` (default: all local devices), or None.

    The runs axis takes the largest device count that divides ``num_runs``; the episodes axis
    takes the largest share of the remaining factor that divides ``num_envs``. Devices that fit
    neither stay idle; with one device (or nothing to split) the result is None.
    """
    devices = list(jax.local_devices() if devices is None else devices)
    runs = math.gcd(num_runs, len(devices))
    episodes = math.gcd(len(devices) // runs, num_envs)
    if runs * episodes == 1:
        return None
    grid = np.asarray(devices[: runs * episodes], dtype=object).reshape(runs, episodes)
    return Mesh(grid, (RUNS, EPISODES))


def is_key(x) -> bool:
    """Whether ``x`` is a typed PRNG key array."""
    return isinstance(x, jax.Array) and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def raw_keys(tree):
    """``tree`` with every PRNG key array replaced by its raw ``key_data``."""
    return jax.tree.map(lambda x: jax.random.key_data(x) if is_key(x) else x, tree)


def place_runs(tree, mesh: Mesh | None):
    """Put a batched state (runs on axis 0 of every leaf) on ``mesh``, replicated over episodes.

    Every process passes the same full values; on several hosts each one keeps its own shards.
    """
    if mesh is None:
        return tree
    sharding = NamedSharding(mesh, PartitionSpec(RUNS))
    if jax.process_count() == 1:
        return jax.device_put(tree, sharding)

    def put(x):
        if is_key(x):
            return jax.random.wrap_key_data(put(jax.random.key_data(x)))
        host = np.asarray(x)
        return jax.make_array_from_callback(host.shape, sharding, lambda idx: host[idx])

    return jax.tree.map(put, tree)


def to_host(tree):
    """Every leaf as a full numpy array on this process (PRNG keys as their raw data).

    On several hosts, leaves that are global arrays (spread over the processes' devices) are
    gathered from every process, so every process must call it; process-local leaves are taken
    as they are.
    """
    raw = raw_keys(tree)
    if jax.process_count() == 1:
        return jax.tree.map(np.asarray, raw)
    from jax.experimental import multihost_utils

    def get(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            return multihost_utils.process_allgather(x, tiled=True)
        return np.asarray(x)

    return jax.tree.map(get, raw)


def use_mesh(mesh: Mesh | None):
    """Context in which :func:`split_episodes` sees ``mesh`` (nothing when it is None)."""
    return jax.set_mesh(mesh) if mesh is not None else contextlib.nullcontext()


def split_episodes(tree, axis: int):
    """Constrain axis ``axis`` (the episode batch) of every leaf to the mesh's episodes axis.

    A no-op outside :func:`use_mesh` or when the mesh does not split episodes, so the rollout
    calls it unconditionally. Under ``vmap(..., spmd_axis_name=RUNS)`` the vmapped run axis is
    added to the constraint by JAX.
    """
    mesh = jax.sharding.get_abstract_mesh()
    if mesh.empty or EPISODES not in mesh.axis_names or mesh.shape[EPISODES] == 1:
        return tree
    spec = PartitionSpec(*([None] * axis), EPISODES)
    return jax.tree.map(lambda x: jax.lax.with_sharding_constraint(x, spec), tree)
