"""The field's Traffic Junction (IC3Net, Singh, Jain and Sukhbaatar, ICLR 2019; after CommNet's)
as a sparsecomm task, in pure JAX: ported from ic3net-envs of the IC3Net repository
(https://github.com/IC3Net/IC3Net, ``ic3net-envs/ic3net_envs/traffic_junction_env.py`` and
``traffic_helper.py``), MIT licence, Copyright (c) 2019 Amanpreet Singh, Tushar Jain and
Sainbayar Sukhbaatar; the licence's full text is in :mod:`sparsecomm.envs.predator_prey`, whose
notice covers this module too.

K cars enter a grid of roads at random, each on a route through the junctions, and leave at
its end. A car's actions: ``0`` gas (one cell along its route), ``1`` brake (stay). The
dynamics, as the original's ``step``:

1. each active car waits one more step (``wait += 1``); on gas it moves one cell along its
   route, and a car that moves past its route's last cell leaves (inactive, parked at cell
   (0, 0), ``wait = 0``); on brake it stays; an inactive car's action is ignored;
2. arrivals: for each entry point in turn, while fewer than K cars are in the system, with
   probability ``arrival_rate`` a car chosen uniformly among the inactive ones enters on a route
   of that entry point chosen uniformly, at its first cell;
3. the observations are read (below);
4. ``reward_i = timestep_penalty * wait_i`` (-0.01 per step in the system), plus
   ``crash_penalty`` (-10) when another car is on its cell (cell (0, 0) excepted), 0 for an
   inactive car; a crash fails the episode.

The episode ends after ``max_steps`` (the original never ends one: IC3Net's trainer cuts it).
**Success** (``info["success"]``): the episode ends now with no crash in it (the original's
``stat["success"] = 1 - has_failed``; ``info["crash_free"]`` is that flag at every step).

**Active cars.** The task has a fixed number of agents K (the original's ``nagents``); cars come
and go, so the state carries ``alive`` (K,) bool and the task offers ``active(state) -> (K,)
bool``: an inactive car's observation is all zeros (as the original gives it; its trainer masks
it), its action is ignored and its reward is 0. Every car is inactive at the start.

**Observation** (the original's ``vocab_type = "bool"``, flattened as IC3Net's ``GymWrapper``
does): the car's last action (0 gas, 1 brake), its route's id divided by ``npath - 1``, and the
``(2 vision + 1)^2`` window of cells around it, each a vector over ``BASE + 3`` entries: the
one-hot of the cell's road index (roads numbered cell by cell, road by road, a later road
overwriting a crossing; ``BASE`` for a cell off the roads or outside the grid) plus the number of
cars on the cell at entry ``BASE + 2`` (inactive cars count, at cell (0, 0), as in the
original). ``BASE`` is the original's: ``2 dim`` (easy; its 7x7 grid has 14 road cells, so road
cells 12 and 13 share entries with "off the road" and the unused ``BASE + 1``, as in the
original), ``4 dim`` (medium), ``8 dim`` (hard).

**Levels** (``TrafficJunctionConfig.level``, IC3Net's README; vision 0 in all):
``easy`` one junction of two one-way roads on a 7x7 grid (``--dim 6``, made odd), 5 cars, 20
steps, 2 routes; ``medium`` one junction of two two-way roads, 14x14, 10 cars, 40 steps, 12
routes; ``hard`` four junctions, 18x18, 20 cars, 80 steps, 56 routes. The arrival rate is a
field; its default is each level's final rate under the README's curriculum (easy 0.3, medium
0.05, hard 0.05; the curriculum itself, which raises the rate with training epochs, is not
ported).

Kept apart on purpose: arrivals are drawn with JAX's random numbers (the original's come from
numpy's global generator); :meth:`TrafficJunction.advance` takes them as arguments, for the
parity test (``tests/test_traffic_junction.py``, against episodes recorded by
``scripts/record_ic3net_parity.py``); the ``scalar`` vocabulary is not ported; docs/field.md.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from sparsecomm.envs.task import TaskConfig

LEVELS = {
    "easy": (6, 5, 0, 20, 0.3),
    "medium": (14, 10, 0, 40, 0.05),
    "hard": (18, 20, 0, 80, 0.05),
}
"""IC3Net's README: level -> (dim, cars, vision, max_steps, the curriculum's final add rate)."""
NUM_ACTIONS = 2
"""Gas (move one cell), brake (stay)."""


@dataclasses.dataclass(frozen=True)
class TrafficJunctionConfig(TaskConfig):
    """IC3Net's Traffic Junction; the grid, the cars and the episode's length come from
    ``level``."""

    level: str = "easy"
    """``easy``, ``medium`` or ``hard`` (see the module docstring). ic3net-envs: IC3Net's
    README's three versions (``--difficulty``); ``easy`` is its first."""
    arrival_rate: float | None = None
    """Probability that a car enters at each entry point each step; None: the level's (easy
    0.3, medium 0.05, hard 0.05). ic3net-envs: ``add_rate``, at the end of the README's
    curriculum (medium's README ``add_rate_max`` 0.02 is below its minimum 0.05, so its rate
    stays 0.05)."""
    timestep_penalty: float = -0.01
    """Reward per step a car has spent in the system. ic3net-envs: ``TIMESTEP_PENALTY``."""
    crash_penalty: float = -10.0
    """Reward of a car on a cell with another. ic3net-envs: ``CRASH_PENALTY``."""

    def __post_init__(self):
        if self.level not in LEVELS:
            raise ValueError(
                f"TrafficJunctionConfig.level must be one of {tuple(LEVELS)}, got {self.level!r}"
            )
        if self.arrival_rate is not None and not (
            isinstance(self.arrival_rate, int | float) and 0.0 <= self.arrival_rate <= 1.0
        ):
            raise ValueError(
                "TrafficJunctionConfig.arrival_rate must be None or in [0, 1], got "
                f"{self.arrival_rate!r}"
            )
        for name in ("timestep_penalty", "crash_penalty"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float | np.number):
                raise ValueError(
                    f"TrafficJunctionConfig.{name} must be a real number, got {value!r}"
                )

    @property
    def num_agents(self) -> int:
        """The cars (the level's)."""
        return LEVELS[self.level][1]

    @property
    def vision(self) -> int:
        """How many cells a car sees on each side (the level's)."""
        return LEVELS[self.level][2]

    @property
    def max_steps(self) -> int:
        """The episode's length limit (the level's)."""
        return LEVELS[self.level][3]

    @property
    def rate(self) -> float:
        """The arrival rate in force."""
        return LEVELS[self.level][4] if self.arrival_rate is None else float(self.arrival_rate)


# -- the original's grid and routes, in numpy, built once per task (traffic_helper.py) ---------

_MOVES = [(-1, 0), (1, 0), (0, -1), (0, 1)]


def _road_blocks(w: int, h: int, level: str):
    return {
        "easy": [np.s_[h // 2, :], np.s_[:, w // 2]],
        "medium": [np.s_[h // 2 - 1 : h // 2 + 1, :], np.s_[:, w // 2 - 1 : w // 2 + 1]],
        "hard": [
            np.s_[h // 3 - 2 : h // 3, :],
            np.s_[2 * h // 3 : 2 * h // 3 + 2, :],
            np.s_[:, w // 3 - 2 : w // 3],
            np.s_[:, 2 * h // 3 : 2 * h // 3 + 2],
        ],
    }[level]


def _add_mat(dims, grid, level):
    h, w = dims
    road_dir = grid.copy()
    junction = np.zeros_like(grid)
    if level == "medium":
        arrival = [(0, w // 2 - 1), (h - 1, w // 2), (h // 2, 0), (h // 2 - 1, w - 1)]
        finish = [(0, w // 2), (h - 1, w // 2 - 1), (h // 2 - 1, 0), (h // 2, w - 1)]
        road_dir[h // 2, :] = 2
        road_dir[h // 2 - 1, :] = 3
        road_dir[:, w // 2] = 4
        junction[h // 2 - 1 : h // 2 + 1, w // 2 - 1 : w // 2 + 1] = 1
    else:
        arrival = [
            (0, w // 3 - 2),
            (0, 2 * w // 3),
            (h // 3 - 1, 0),
            (2 * h // 3 + 1, 0),
            (h - 1, w // 3 - 1),
            (h - 1, 2 * w // 3 + 1),
            (h // 3 - 2, w - 1),
            (2 * h // 3, w - 1),
        ]
        finish = [
            (0, w // 3 - 1),
            (0, 2 * w // 3 + 1),
            (h // 3 - 2, 0),
            (2 * h // 3, 0),
            (h - 1, w // 3 - 2),
            (h - 1, 2 * w // 3),
            (h // 3 - 1, w - 1),
            (2 * h // 3 + 1, w - 1),
        ]
        road_dir[h // 3 - 1, :] = 2
        road_dir[2 * h // 3, :] = 3
        road_dir[2 * h // 3 + 1, :] = 4
        road_dir[:, w // 3 - 2] = 5
        road_dir[:, w // 3 - 1] = 6
        road_dir[:, 2 * w // 3] = 7
        road_dir[:, 2 * w // 3 + 1] = 8
        junction[h // 3 - 2 : h // 3, w // 3 - 2 : w // 3] = 1
        junction[2 * h // 3 : 2 * h // 3 + 2, w // 3 - 2 : w // 3] = 1
        junction[h // 3 - 2 : h // 3, 2 * w // 3 : 2 * w // 3 + 2] = 1
        junction[2 * h // 3 : 2 * h // 3 + 2, 2 * w // 3 : 2 * w // 3 + 2] = 1
    return arrival, finish, road_dir, junction


def _next_move(curr, turn, turn_step, start, grid, road_dir, junction, visited):
    h, w = grid.shape
    turn_completed = turn_prog = False
    neigh = []
    for m in _MOVES:
        n = (curr[0] + m[0], curr[1] + m[1])
        if not (0 <= n[0] <= h - 1 and 0 <= n[1] <= w - 1 and grid[n] and n not in visited):
            continue
        if junction[n] == junction[curr] == 1:
            if (turn == 0 or turn == 2) and ((n[0] == start[0]) or (n[1] == start[1])):
                neigh.append(n)
                if turn == 2:
                    turn_prog = True
            elif turn == 2 and turn_step == 1:
                neigh.append(n)
                turn_prog = True
        elif (
            junction[curr]
            and not junction[n]
            and turn == 2
            and turn_step == 2
            and (abs(start[0] - n[0]) == 2 or abs(start[1] - n[1]) == 2)
        ):
            neigh.append(n)
            turn_completed = True
        elif junction[n] and not junction[curr]:
            neigh.append(n)
        elif turn == 1 and not junction[n] and junction[curr]:
            neigh.append(n)
            turn_completed = True
        elif turn == 0 and junction[curr] and road_dir[n] == road_dir[start]:
            neigh.append(n)
            turn_completed = True
        elif road_dir[n] == road_dir[curr] and not junction[curr]:
            neigh.append(n)
    if not neigh:
        raise RuntimeError("no next move: an ambiguous route")
    return neigh[0], turn_prog, turn_completed


def _routes_turning(dims, grid, level):
    """The original's ``get_routes``: for each entry point, its routes (lists of cells)."""
    arrival, finish, road_dir, junction = _add_mat(dims, grid, level)
    n_turn2 = 1 if level == "medium" else 3
    routes = []
    for i in range(len(arrival)):
        others = finish[:i] + finish[i + 1 :]
        paths = []
        for turn_1 in range(3):  # straight, right, left
            for turn_2 in range(n_turn2):
                total_turns, curr_turn, turn_step = 0, turn_1, 0
                current = start = arrival[i]
                path, visited = [current], set()
                while current not in others:
                    visited.add(current)
                    current, prog, completed = _next_move(
                        current, curr_turn, turn_step, start, grid, road_dir, junction, visited
                    )
                    if curr_turn == 2 and prog:
                        turn_step += 1
                    if completed:
                        total_turns += 1
                        curr_turn, turn_step, start = turn_2, 0, current
                    if total_turns == 2:
                        curr_turn = 0
                    path.append(current)
                paths.append(path)
                if total_turns == 1:
                    break
        routes.append(paths)
    return routes


def layout(level: str):
    """The original's grid of cell classes ``(H, W)``, ``BASE`` and routes (a list per entry
    point of (L, 2) arrays), for ``level``."""
    dim = LEVELS[level][0]
    base = {"easy": 2 * dim, "medium": 4 * dim, "hard": 8 * dim}[level]
    size = dim + 1 if level == "easy" else dim
    h = w = size
    grid = np.full((h, w), base, np.int64)
    roads = _road_blocks(w, h, level)
    for road in roads:
        grid[road] = 1
    route_grid = grid.copy()
    start = 0
    for road in roads:
        sz = int(np.prod(grid[road].shape))
        grid[road] = np.arange(start, start + sz).reshape(grid[road].shape)
        start += sz
    if level == "easy":
        routes = [[[(i, w // 2) for i in range(h)]], [[(h // 2, i) for i in range(w)]]]
    else:
        routes = _routes_turning((h, w), route_grid, level)
    return grid, base, [[np.array(p, np.int32) for p in group] for group in routes]


@struct.dataclass
class TrafficJunctionState:
    """The cars and the episode's bookkeeping."""

    loc: jax.Array
    """(K, 2) int32 (row, column) of each car; (0, 0) for an inactive one."""
    alive: jax.Array
    """(K,) bool: the car is in the system (active)."""
    wait: jax.Array
    """(K,) int32 steps the car has spent in the system."""
    route: jax.Array
    """(K,) int32 the car's route (index into the task's table of routes)."""
    route_id: jax.Array
    """(K,) int32 the original's route id (``path + entry * routes per entry``); -1 before a
    car first enters."""
    route_loc: jax.Array
    """(K,) int32 the car's position along its route."""
    last_act: jax.Array
    """(K,) int32 the car's last action while active (0 gas, 1 brake)."""
    failed: jax.Array
    """() bool: a crash happened in this episode."""
    time: jax.Array
    """() int32 steps taken."""
    done: jax.Array
    """() bool, the episode is over; sticky."""


class TrafficJunction:
    """IC3Net's Traffic Junction with the task interface (see the module docstring)."""

    def __init__(self, config: TrafficJunctionConfig | None = None):
        self.config = TrafficJunctionConfig() if config is None else config
        grid, base, routes = layout(self.config.level)
        v = self.config.vision
        self.base = base
        self.vocab = base + 3
        self.car_class = base + 2
        self.routes = routes
        self.npath = {"easy": 2, "medium": 12, "hard": 56}[self.config.level]
        self._classes = np.pad(grid, v, constant_values=base).astype(np.int32)
        paths = [p for group in routes for p in group]
        longest = max(len(p) for p in paths)
        self._paths = np.stack([np.pad(p, ((0, longest - len(p)), (0, 0))) for p in paths])
        self._lengths = np.array([len(p) for p in paths], np.int32)
        self._first = np.cumsum([0] + [len(g) for g in routes])[:-1].astype(np.int32)

    def __repr__(self) -> str:
        return f"TrafficJunction({self.config!r})"

    @property
    def num_agents(self) -> int:
        return self.config.num_agents

    @property
    def num_actions(self) -> int:
        return NUM_ACTIONS

    @property
    def max_steps(self) -> int:
        return self.config.max_steps

    @property
    def num_entries(self) -> int:
        """Entry points (the original's route groups)."""
        return len(self.routes)

    @property
    def obs_dim(self) -> int:
        """Last action, route id, and the window's cells over the vocabulary."""
        return 2 + (2 * self.config.vision + 1) ** 2 * self.vocab

    @property
    def state_dim(self) -> int:
        """Size of :meth:`global_state`: each car's cell, activity, wait and route, and the
        time."""
        return 5 * self.num_agents + 1

    def _obs(self, s: TrafficJunctionState) -> jax.Array:
        v = self.config.vision
        w = 2 * v + 1
        n = self._classes.shape
        cars = jnp.zeros(n, jnp.float32).at[s.loc[:, 0] + v, s.loc[:, 1] + v].add(1.0)
        classes = jnp.asarray(self._classes)
        route_ids = jnp.asarray((np.arange(self.npath) / (self.npath - 1)).astype(np.float32))

        def one(loc, alive, last, rid):
            def cut(x):
                return jax.lax.dynamic_slice(x, (loc[0], loc[1]), (w, w))

            cells = jax.nn.one_hot(cut(classes), self.vocab, dtype=jnp.float32)
            cells = cells.at[..., self.car_class].add(cut(cars))
            # the original's float64 quotient, rounded once to float32
            head = jnp.stack([last.astype(jnp.float32), route_ids[jnp.maximum(rid, 0)]])
            return jnp.where(alive, jnp.concatenate([head, cells.reshape(-1)]), 0.0)

        return jax.vmap(one)(s.loc, s.alive, s.last_act, s.route_id)

    def reset(self, key: jax.Array) -> tuple[jax.Array, TrafficJunctionState]:
        """No car in the system (as the original): every car inactive, all observations 0."""
        k = self.num_agents
        zeros = jnp.zeros((k,), jnp.int32)
        state = TrafficJunctionState(
            jnp.zeros((k, 2), jnp.int32),
            jnp.zeros((k,), bool),
            zeros,
            zeros,
            jnp.full((k,), -1, jnp.int32),
            zeros,
            zeros,
            jnp.zeros((), bool),
            jnp.zeros((), jnp.int32),
            jnp.zeros((), bool),
        )
        return self._obs(state), state

    def active(self, state: TrafficJunctionState) -> jax.Array:
        """(K,) bool: the cars in the system now."""
        return state.alive

    def _draw(self, key: jax.Array, alive: jax.Array, entry: int):
        """One entry point's arrival: (car or -1, path) -- a uniform inactive car with
        probability ``rate``, on a uniform route of the entry point."""
        k_add, k_car, k_path = jax.random.split(key, 3)
        dead = ~alive
        noise = jax.random.uniform(k_car, alive.shape)
        car = jnp.argmax(jnp.where(dead, noise, -1.0)).astype(jnp.int32)
        arrive = (jax.random.uniform(k_add) <= self.config.rate) & jnp.any(dead)
        path = jax.random.randint(k_path, (), 0, len(self.routes[entry]))
        return jnp.where(arrive, car, -1), path.astype(jnp.int32)

    def step(self, key: jax.Array, state: TrafficJunctionState, actions: jax.Array):
        """One step (the module docstring's 1-4), arrivals drawn from ``key``. Returns ``(obs,
        state, rewards (K,), dones (K,), info)``; ``info["success"]``: the episode ends now with
        no crash; ``info["crash_free"]``: no crash so far."""
        return self.advance(state, actions, key=key)

    def advance(self, state: TrafficJunctionState, actions: jax.Array, arrivals=None, key=None):
        """:meth:`step` with the arrivals given: ``arrivals`` (entries, 2) int, for each entry
        point in turn the car that enters (-1: none) and its route among the entry point's
        (the parity test replays the original's); or drawn from ``key``."""
        c = self.config
        k = self.num_agents
        acts = actions.astype(jnp.int32)
        paths, lengths = jnp.asarray(self._paths), jnp.asarray(self._lengths)
        live = state.alive & ~state.done
        # 1. the cars act
        wait = state.wait + live.astype(jnp.int32)
        gas = live & (acts == 0)
        brake = live & (acts == 1)
        route_loc = state.route_loc + gas.astype(jnp.int32)
        leaves = gas & (route_loc == lengths[state.route])
        cell = paths[state.route, jnp.minimum(route_loc, paths.shape[1] - 1)]
        loc = jnp.where((gas & ~leaves)[:, None], cell, state.loc)
        loc = jnp.where(leaves[:, None], 0, loc)
        alive = state.alive & ~leaves
        wait = jnp.where(leaves, 0, wait)
        last_act = jnp.where(brake, 1, jnp.where(gas & ~leaves, 0, state.last_act))
        route, route_id = state.route, state.route_id
        # 2. arrivals, entry by entry, while fewer than K cars are in the system
        keys = None if key is None else jax.random.split(key, self.num_entries)
        for entry in range(self.num_entries):
            if arrivals is None:
                car, path = self._draw(keys[entry], alive, entry)
            else:
                car, path = arrivals[entry, 0], arrivals[entry, 1]
            add = (car >= 0) & (jnp.sum(alive) < k) & ~state.done
            this = add & (jnp.arange(k) == car)
            r = self._first[entry] + path
            alive = alive | this
            route = jnp.where(this, r, route)
            route_id = jnp.where(this, path + entry * len(self.routes[entry]), route_id)
            route_loc = jnp.where(this, 0, route_loc)
            loc = jnp.where(this[:, None], paths[r, 0], loc)
        # 3.-4. observations and rewards
        same = jnp.all(loc[:, None] == loc[None], -1) & ~jnp.eye(k, dtype=bool)
        crash = jnp.any(same, -1) & jnp.any(loc != 0, -1)
        # The original's float64 sums, rounded once to float32 (by wait, crash or not).
        waits = np.arange(c.max_steps + 1)
        table = np.stack([c.timestep_penalty * waits, c.timestep_penalty * waits + c.crash_penalty])
        table = jnp.asarray(table.astype(np.float32))
        rewards = table[crash.astype(jnp.int32), jnp.minimum(wait, c.max_steps)]
        rewards = jnp.where(alive & ~state.done, rewards, 0.0).astype(jnp.float32)
        failed = state.failed | (jnp.any(crash) & ~state.done)
        time = state.time + jnp.where(state.done, 0, 1).astype(jnp.int32)
        done = state.done | (time >= c.max_steps)
        new = TrafficJunctionState(
            loc, alive, wait, route, route_id, route_loc, last_act, failed, time, done
        )
        new = jax.tree.map(lambda a, b: jnp.where(state.done, a, b), state, new)
        info = {"success": done & ~state.done & ~failed, "crash_free": ~new.failed}
        return self._obs(new), new, rewards, jnp.full((k,), new.done), info

    def global_state(self, state: TrafficJunctionState) -> jax.Array:
        """(state_dim,) float32 for the centralised critic: each car's cell (scaled to [0, 1]),
        activity, wait (over max_steps) and route id (over the routes), and the time."""
        scale = 1.0 / (self._classes.shape[0] - 1)
        return jnp.concatenate(
            [
                state.loc.reshape(-1) * scale,
                state.alive,
                state.wait / self.config.max_steps,
                state.route_id / (self.npath - 1),
                (state.time / self.config.max_steps)[None],
            ]
        ).astype(jnp.float32)

    def positions(self, state: TrafficJunctionState) -> jax.Array:
        """(K, 2) float32 the cars' (row, column) cells ((0, 0) for an inactive car)."""
        return state.loc.astype(jnp.float32)
