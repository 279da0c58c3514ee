"""Scale-out with ``jax.sharding``: the runs of a sweep and the episodes of a run over devices.

A sweep is a batch of independent runs (seeds x lambdas), and every run's update plays a batch of
independent episodes. :func:`make_mesh` lays the devices out as a 2-D mesh ``(runs, episodes)``:
runs are split over the first axis, each run's episodes over the second, and a run's parameters
are replicated along it. :func:`place_runs` puts the batched training state on the mesh, and
:func:`split_episodes` (called by the rollout on its batch axis) tells XLA to partition the
episodes. XLA's SPMD partitioner then inserts the one collective this needs: the sum of each
run's gradients over its episode shards. Nothing else is exchanged, so the results equal a
single-device run up to float summation order.

On one machine without an accelerator the ``sparsecomm`` command gives JAX one CPU device per
usable core (:func:`use_host_cores`) and the commands hand a sweep only as many of them as split
its runs evenly (:func:`sweep_devices`): runs on separate host devices train side by side, but
one run's episodes split over them were slower than on one device (docs/benchmarks.md).

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
import os
from collections.abc import Sequence

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from sparsecomm.cmdline import check_device_counts

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

    def __post_init__(self):
        n, i = self.num_processes, self.process_id
        for name, value in (("num_processes", n), ("process_id", i)):
            if value is not None and (isinstance(value, bool) or not isinstance(value, int)):
                raise ValueError(f"distributed.{name} must be an integer or None, got {value!r}")
        if n is not None and n < 1:
            raise ValueError(f"distributed.num_processes must be an integer >= 1, got {n}")
        if i is not None and n is not None and not 0 <= i < n:
            raise ValueError(
                f"distributed.process_id must be in [0, {n - 1}] (num_processes {n}), got {i}"
            )
        if i is not None and i < 0:
            raise ValueError(f"distributed.process_id must be an integer >= 0, got {i}")

    def initialize(self) -> None:
        """Join the cluster (a no-op unless ``enabled``). CPU collectives go over gloo."""
        if not self.enabled:
            return
        n, i = self.num_processes, self.process_id
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize(self.coordinator_address, n, i)


def is_primary() -> bool:
    """Whether this process writes the files (logs, checkpoints, results): process 0 under
    ``jax.distributed``, always with one process."""
    return jax.process_index() == 0


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity mask where the OS has one)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def use_host_cores() -> int | None:
    """Give JAX one CPU device per usable core, unless the user chose a count.

    The user's choice is ``JAX_NUM_CPU_DEVICES`` (``1``: everything on one device) or
    ``--xla_force_host_platform_device_count`` in ``XLA_FLAGS``; either one leaves JAX as it
    is. Must run before JAX computes anything (the ``sparsecomm`` command calls it first; a
    library user calls it, or sets ``JAX_NUM_CPU_DEVICES``, before any JAX work).
    Accelerators are unaffected: the CPU devices only serve where JAX has no other platform.
    Two host devices on a 2-core VM trained a 10-run sweep 1.55x and a 20-run sweep 1.39x
    faster per update (docs/benchmarks.md). The count changes the compiled programs, so a sweep
    gives the same numbers again on the same device count, not across counts.

    A count that is not a positive integer is refused with a ``ValueError`` naming the variable
    (:func:`sparsecomm.cmdline.check_device_counts`; the command checks it before importing JAX,
    which fails on one it cannot read).

    Returns:
        The device count set, or None where the user's choice was kept.
    """
    check_device_counts()
    if "JAX_NUM_CPU_DEVICES" in os.environ:
        return None
    if "xla_force_host_platform_device_count" in os.environ.get("XLA_FLAGS", ""):
        return None
    cores = usable_cores()
    jax.config.update("jax_num_cpu_devices", cores)
    return cores


def fast_compile(on: bool) -> bool:
    """Set ``jax_disable_most_optimizations``: programs compile several times faster and run
    about 3x slower. Returns its previous value."""
    try:
        previous = bool(jax.config._read("jax_disable_most_optimizations"))
    except (AttributeError, KeyError):
        previous = False
    jax.config.update("jax_disable_most_optimizations", on)
    return previous


def sweep_devices(num_runs: int, devices: Sequence | None = None) -> list:
    """The devices the commands give a sweep (or an evaluation) of ``num_runs`` runs.

    All of ``devices`` (default: every process's) on accelerators and under
    ``jax.distributed``; on one process's CPU devices, the first ``gcd(num_runs, n)``, which
    split the runs evenly and leave every run's episodes whole: a machine's CPU devices share
    its cores, and a 5-run sweep with its episodes split over two of them was ~14% slower per
    update than on one device (docs/benchmarks.md).
    """
    devices = list(jax.devices() if devices is None else devices)
    if jax.process_count() > 1 or devices[0].platform != "cpu":
        return devices
    return devices[: math.gcd(num_runs, len(devices))]


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


def runs_on_devices(tree, mesh: Mesh | None):
    """``tree`` (runs on axis 0 of every leaf, global arrays) laid out as :func:`place_runs`
    lays it, whatever its layout now, through a jitted identity (so it works on several hosts
    too). A compiled chunk returns its state laid out so; a state laid out otherwise (``init``
    returns some parts replicated) would make the chunk compile a second time."""
    if mesh is None:
        return tree
    return jax.jit(lambda t: t, out_shardings=NamedSharding(mesh, PartitionSpec(RUNS)))(tree)


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
