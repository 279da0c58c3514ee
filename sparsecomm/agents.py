"""Networks: a recurrent actor per agent and a centralised critic (SPEC section 5).

The actor of agent i reads its observation and the messages it received at the previous step,
updates a GRU state, and outputs action logits and the signal ``z^{i->j}`` in [0, 1]^C for every
recipient j != i. By default the agents share one set of actor parameters and each reads a
one-hot agent id beside its observation; with ``AgentConfig.share_params = False`` (the paper's
choice) each agent has its own parameters, stacked on a leading agent axis and applied with
``vmap`` (one batched matmul per layer for the whole team).
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from sparsecomm.channel import gate
from sparsecomm.channel.team import TeamChannel
from sparsecomm.configs import AgentConfig, ExperimentalConfig
from sparsecomm.scaling import AttentionPool, check_fits, inbox_features


def orthogonal(scale: float = 1.0, iterations: int = 60):
    """Initializer for a Haar-random orthogonal matrix without LAPACK.

    The polar factor of a Gaussian matrix is Haar-distributed (what ``nn.initializers.orthogonal``
    draws via QR). We compute it with the Newton-Schulz iteration ``X <- X (3I - X^T X) / 2``,
    matmuls only. Reason: batched QR custom calls under ``vmap`` (seeds x agents) intermittently
    deadlocked XLA's CPU runtime (jax 0.10.2), see docs/notes.md.
    """

    def init(key, shape, dtype=jnp.float32):
        rows, cols = shape[-2], shape[-1]
        tall = rows >= cols
        a = jax.random.normal(key, shape if tall else (*shape[:-2], cols, rows), jnp.float32)
        a = a / jnp.linalg.norm(a, axis=(-2, -1), keepdims=True)  # singular values in (0, 1]

        def step(x, _):
            return 1.5 * x - 0.5 * x @ (jnp.swapaxes(x, -1, -2) @ x), None

        q, _ = jax.lax.scan(step, a, None, length=iterations)
        if not tall:
            q = jnp.swapaxes(q, -1, -2)
        return (scale * q).astype(dtype)

    return init


class Actor(nn.Module):
    """One agent's recurrent policy with an action head and a message head."""

    hidden: int
    gru: int
    num_actions: int
    num_recipients: int
    num_elements: int  # of each link's signal, its gate included (ChannelConfig.signal_elements)
    message_bias_init: float = 0.0
    message_gate: str = "sigmoid"
    attention: bool = False
    gate_bias_init: float | None = None  # the last element of each link is its gate: its bias

    @nn.compact
    def __call__(self, carry: jax.Array, x: jax.Array, inbox=None, heard=None):
        if self.attention:  # ``AgentConfig.aggregate = "attention"``: pool the inbox first
            x = jnp.concatenate([x, AttentionPool(name="attention")(carry, inbox, heard)], -1)
        h = nn.relu(nn.Dense(self.hidden)(x))
        h = nn.relu(nn.Dense(self.hidden)(h))
        carry, h = nn.GRUCell(self.gru, recurrent_kernel_init=orthogonal())(carry, h)
        logits = nn.Dense(self.num_actions)(h)
        bias = nn.initializers.constant(self.message_bias_init)
        if self.gate_bias_init is not None:
            bias = self._gated_bias
        a = nn.Dense(self.num_recipients * self.num_elements, bias_init=bias, name="message")(h)
        z = gate(self.message_gate, a)
        z = z.reshape(*z.shape[:-1], self.num_recipients, self.num_elements)
        return carry, logits, z

    def _gated_bias(self, key, shape, dtype=jnp.float32):
        """The message head's initial bias: ``message_bias_init``, and ``gate_bias_init`` on
        each link's gate (the last of its elements)."""
        per_link = jnp.full((self.num_recipients, self.num_elements), self.message_bias_init)
        return per_link.at[:, -1].set(self.gate_bias_init).reshape(shape).astype(dtype)


class Critic(nn.Module):
    """Centralised value function: full state -> one value per agent."""

    hidden: int
    num_agents: int

    @nn.compact
    def __call__(self, s: jax.Array) -> jax.Array:
        h = nn.relu(nn.Dense(self.hidden)(s))
        h = nn.relu(nn.Dense(self.hidden)(h))
        return nn.Dense(self.num_agents)(h)


class Team:
    """The K actors (separate or shared parameters) and the critic, as pure functions."""

    def __init__(
        self,
        cfg: AgentConfig,
        num_agents: int,
        obs_dim: int,
        num_actions: int,
        links: TeamChannel,
        state_dim: int,
        experimental: ExperimentalConfig | None = None,
    ):
        """``links``: the team's channel (``channel.build``): each link's C message
        elements and the gate the head emits beside them (``links.signal_elements``), and the
        width of the inbox each actor reads (``links.inbox_width``: every link's message,
        news flags under ``on_silence = "hold"``, and with ``AgentConfig.reads_sent`` what the
        agent's own links last delivered). ``experimental``: the message head's initial
        biases and whether only the live links are computed (``ExperimentalConfig``)."""
        check_fits(cfg, num_agents)
        if links.news_inputs and cfg.aggregate != "concat":
            raise ValueError(
                "ChannelConfig.on_silence 'hold' needs AgentConfig.aggregate 'concat', got "
                f"{cfg.aggregate!r}"
            )
        if cfg.reads_sent != links.reads_sent:
            raise ValueError("the team's channel must be built with AgentConfig.reads_sent")
        num_elements = links.cfg.num_elements
        self.cfg = cfg
        self.num_agents = num_agents
        self.num_actions = num_actions
        self.num_elements = num_elements
        self.links = links
        experimental = ExperimentalConfig() if experimental is None else experimental
        self.experimental = experimental
        """The message head's initial biases, and whether only live links are computed."""
        """The team's own channel (``channel.build``)."""
        self.reads_sent = cfg.reads_sent
        """Each actor's inbox ends with the last message each of its own links delivered."""
        self.routed = cfg.neighbours is not None or cfg.radius is not None
        """Links follow the agents' positions (``sparsecomm.scaling.routing_mask``)."""
        inbox_sizes = {
            "concat": links.inbox_width(),  # every link's message, and its own links'
            "mean": num_elements + 1,  # their mean and the fraction of the team heard
            "attention": 1,  # the fraction heard; the attention's pool is added in the actor
        }
        self.msg_in = inbox_sizes[cfg.aggregate]
        """Inputs the actor's first layer reads from the inbox."""
        self.in_dim = obs_dim + self.msg_in + (num_agents if cfg.share_params else 0)
        self.state_dim = state_dim
        self.actor = Actor(
            cfg.hidden,
            cfg.gru,
            num_actions,
            num_agents - 1,
            links.signal_elements,
            experimental.message_bias_init,
            cfg.message_gate,
            cfg.aggregate == "attention",
            experimental.gate_bias_init if links.gated else None,
        )
        self.critic = Critic(cfg.critic_hidden, num_agents)

    def init(self, key: jax.Array) -> dict:
        k_actor, k_critic = jax.random.split(key)
        carry = jnp.zeros((1, self.cfg.gru))
        x = jnp.zeros((1, self.in_dim))
        inbox = jnp.zeros((1, self.num_agents - 1, self.num_elements))
        heard = jnp.ones((1, self.num_agents - 1), bool)
        if self.cfg.share_params:
            actor = self.actor.init(k_actor, carry, x, inbox, heard)
        else:
            keys = jax.random.split(k_actor, self.num_agents)
            actor = jax.vmap(lambda k: self.actor.init(k, carry, x, inbox, heard))(keys)
        critic = self.critic.init(k_critic, jnp.zeros((1, self.state_dim)))
        return {"actor": actor, "critic": critic}

    def initial_carry(self, batch: int) -> jax.Array:
        return jnp.zeros((batch, self.num_agents, self.cfg.gru))

    def act(self, actor_params, carry: jax.Array, obs: jax.Array, msgs: jax.Array, heard=None):
        """One step of every actor.

        Args: ``carry`` (B, K, H); ``obs`` (B, K, obs_dim); ``msgs`` (B, K, (K-1) C) decoded
        messages received at the previous step, by recipient (``channel.deliver``; under
        ``on_silence = "hold"`` then K-1 news inputs, and with ``reads_sent`` the (K-1) C
        messages the agent's own links last delivered, by slot: :attr:`msg_in` in all); ``heard``
        (B, K, K-1) bool, which of them arrived (routing, ``sparsecomm.scaling``; None: all).
        ``mean`` and ``attention`` also take a gathered inbox, only the k links each recipient
        is listed (``msgs`` (B, K, k C), ``heard`` (B, K, k); ``channel.listed``).
        ``concat`` reads ``msgs`` whole; ``mean`` and ``attention`` only the heard ones.
        Returns ``(carry, logits (B, K, A), z (B, K, K-1, C))``.
        """
        inbox = None
        if self.cfg.aggregate == "concat":
            x = jnp.concatenate([obs, msgs], axis=-1)
        else:
            # the K - 1 other agents' links, or only the links a gathered layout lists
            inbox = msgs.reshape(*msgs.shape[:-1], -1, self.num_elements)
            if heard is None:
                heard = jnp.ones(inbox.shape[:-1], bool)
            others = self.num_agents - 1
            x = jnp.concatenate([obs, inbox_features(inbox, heard, self.cfg.aggregate, others)], -1)
        if self.cfg.share_params:
            ids = jnp.broadcast_to(jnp.eye(self.num_agents), (*x.shape[:-1], self.num_agents))
            x = jnp.concatenate([x, ids], axis=-1)
            if inbox is None:
                return self.actor.apply(actor_params, carry, x)
            return self.actor.apply(actor_params, carry, x, inbox, heard)
        if inbox is None:
            return jax.vmap(self.actor.apply, in_axes=(0, 1, 1), out_axes=1)(actor_params, carry, x)
        return jax.vmap(self.actor.apply, in_axes=(0, 1, 1, 1, 1), out_axes=1)(
            actor_params, carry, x, inbox, heard
        )

    def message_penalty(self, head_params, hidden: jax.Array, penalty) -> jax.Array:
        """The bit penalty of the messages the head ``head_params`` (the actors' ``message``
        layer) emits from GRU states ``hidden`` (..., K, H): summed over each agent's links and
        elements, (..., K). The same numbers as the rollout's penalty for the same states, as a
        function of the head alone (for a penalty step outside the optimiser). ``penalty``: the
        channel's cost of each link, (..., C) -> (...) (``ChannelConfig.link_penalty``)."""
        kernel, bias = head_params["kernel"], head_params["bias"]
        if self.cfg.share_params:
            a = hidden @ kernel + bias
        else:  # one head per agent, stacked on a leading agent axis
            a = jnp.einsum("...kh,khm->...km", hidden, kernel) + bias
        z = gate(self.cfg.message_gate, a)
        links = z.reshape(*z.shape[:-1], self.num_agents - 1, -1)  # (..., K, K-1, C)
        return penalty(links).sum(-1)

    def value(self, critic_params, state: jax.Array) -> jax.Array:
        """(..., state_dim) -> (..., K) values."""
        return self.critic.apply(critic_params, state)
