"""How a team talks: :class:`ChannelConfig`, and the capabilities of its mode.

Callers outside ``channel/`` ask a config what its mode does (``speaks``, ``quantizes``,
``samples_symbols``, ``sends_symbols``, ``sends_values``, ``has_penalty``, ``deployable``)
instead of comparing its ``mode`` string, so a new mode is written in ``channel/`` alone.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from sparsecomm.channel.codes import CODE_NAMES, Code, frequency_remap
from sparsecomm.channel.ecc import ECC_NAMES
from sparsecomm.channel.fitted import FittedCode
from sparsecomm.channel.frames import CHECK_BITS
from sparsecomm.channel.noise import NoiseConfig
from sparsecomm.channel.penalty import code_penalty, expected_frame_bits
from sparsecomm.channel.quantizer import check_levels

CHANNEL_MODES = ("discrete", "continuous", "off", "reinforced")
PRICES = ("payload", "wire")
"""What the bit penalty prices and a bit budget counts (``ChannelConfig.prices``)."""
ON_SILENCE = ("null", "hold")
"""What a receiver makes of a silent link (``ChannelConfig.on_silence``)."""
CHANNEL_CODES = (*CODE_NAMES[:2], "fitted", "remapped", "permuted")


@dataclasses.dataclass(frozen=True)
class ChannelConfig:
    """The message channel between agents (docs/spec.md sections 1-3)."""

    mode: str = "discrete"
    """``discrete``: dithered quantization, the paper's method. ``continuous``: real-valued
    messages sent as float32 (a baseline, 32 bits per element). ``off``: no communication
    (messages are zeros, 0 bits; a baseline). ``reinforced``: reinforced communication learning
    (RCL, a baseline): each element's symbol is sampled as an action, m ~ Binomial(levels, z),
    the receiver gets m / levels with no gradient through the channel, and the senders learn by
    policy gradient on the log-probability of the symbols sent, with ``bit_cost`` per bit."""
    levels: int = 15
    """|M|, symbols per element are {0, ..., levels}. SPEC section 1."""
    num_elements: int = 10
    """C, elements of the signal z each agent sends to each recipient per step. Paper: 10."""
    code: str = "paper"
    """Code used to count payload bits (and frame them on the wire) for the ``discrete`` and
    ``reinforced`` modes:
    ``paper`` (the paper's variable-length code, Elias-gamma framing), ``fixed`` (fixed-width,
    a baseline), ``fitted`` (a code fitted to a trained team's symbols, read from
    ``code_file``: payload bits and the penalty stay the paper's, wire bits are the fitted
    code's packets; ``sparsecomm.channel.fitted``) or ``remapped`` (a learned code: the paper's
    code with each element's symbols ranked by how often the team of ``code_file`` sends them,
    the most frequent getting the shortest codeword; payload bits and the penalty, the exact
    expected codeword bits, price the remapped lengths; ``Code.remap``). SPEC section 2."""
    code_file: str = ""
    """``code = fitted`` or ``remapped`` only: the JSON file of a fitted code (``sparsecomm
    fit-code``). A fitted code's SHA-256 fingerprint is checked by every packet's CRC."""
    noise: NoiseConfig = NoiseConfig()
    """Noise on every link's packets (``sparsecomm.channel.noise``): bit flips, erasure, bursts,
    delay; a packet with a flipped bit fails its CRC-32 and is lost, and the receiver uses the
    null message or its last good one (``noise.on_drop``). Applied in training and evaluation
    alike (``sparsecomm eval --noise.*`` evaluates a team under other noise). ours: none."""
    ecc: str = "none"
    """Error correction on every packet (``sparsecomm.channel.ecc``): ``none``, or
    ``hamming74`` (each 4 bits of a packet sent as 7, correcting one flipped bit per block; the
    redundancy, 1.75x plus padding, is counted in the wire bits). ours: ``none``."""
    bit_cost: float = 0.0
    """``reinforced`` mode only: reward subtracted from agent i at step t per payload bit it
    sends (paper reward units, scaled by ``reward_scale`` like the task reward; not included in
    the logged group reward). Neither the paper nor SPEC gives a value; ours: 0 (no cost), and
    ``sparsecomm reproduce`` uses 0.001, the price per bit that the surrogate penalty sets at
    lambda = 0.001 (lambda is in the same units, see ``sparsecomm.rl``)."""
    prices: str = "payload"
    """What the bit penalty prices and a bit budget (``BudgetConfig.bits``) counts, per step:
    ``payload``, the paper's codeword bits (its penalty ``log2(levels z + 1)`` per element), or
    ``wire``, every bit a sender's frame carries, recipient map, presence bitmaps, padding and
    check included (its penalty the exact expected frame bits of each sender under the dither,
    ``channel.expected_frame_bits``, shared equally by the sender's links, so falling silent
    is what saves most). ``wire`` needs the ``discrete`` mode, the ``paper`` or ``fixed`` code
    and no ``ecc``. Paper: ``payload``; both counts are logged either way."""
    check_bits: int = 32
    """Width in bits of the integrity check of each sender's frame (``channel.frames``): one of
    ``channel.CHECK_BITS`` (0, 8, 16, 32). A corrupted frame passes a w-bit check with
    probability about 2^-w (measured by ``benchmarks/frame_fuzz.py``, docs/wire.md); a frame
    that fails it is lost. ours: 32, the CRC-32 every packet carried before frames (the paper
    sends no packets)."""
    link_gate: bool = False
    """Each link gets one more signal element from the message head, ``g`` in [0, 1]: whether
    the link speaks this step, quantized with its own dither (1 with probability exactly ``g``,
    straight-through gradient, as the other elements). A closed gate makes every element of the
    link null, so the link sends nothing; the penalty is ``g`` times the link's price, a smooth
    price of speaking at all where the elements' own chance of all being null has none (it is 0
    as soon as one element exceeds ``1 / levels``). ``discrete`` mode, no delay. ours:
    ``False`` (the paper has no gate; docs/wire.md)."""
    on_silence: str = "null"
    """What a receiver makes of a link that sent nothing this step: ``null``, the null message
    (all-null symbols rebuilt with the link's dither; the paper's), or ``hold``, the last
    message the link did send (zeros before the first), and each recipient also reads, per
    link, whether this step's message is news (1) or held (0). Under ``hold`` a lost packet is
    held too (a receiver that gets nothing cannot tell silence from loss). ``hold``: the
    ``discrete`` mode, no delay, the ``concat`` inbox. Paper: ``null``."""
    news_margin: float | None = None
    """Event-triggered links: with ``link_gate`` and ``on_silence = "hold"``, a link's gate
    also opens when what it would say differs from what its recipient holds:
    ``g <- max(g, clip((d - news_margin) / news_margin, 0, 1))`` with ``d = max_k |z_k - h_k|``
    over the link's C elements, ``h`` the last message the link delivered (zeros before the
    first; the sender knows it: the shared dither rebuilds it on both sides). A link then
    speaks when it has news without having to learn when news comes, and the price teaches its
    signal to stay put when there is none (``channel.news_gate``). In signal units (z in
    [0, 1]), in (0, 1]; the quantizer's own error is at most ``0.5 / levels``. ``None``: the
    learned gate alone. ours: ``None``, what runs before this field did (docs/wire.md)."""

    def __post_init__(self):
        if self.mode not in CHANNEL_MODES:
            raise _bad("mode", self.mode, f"one of {CHANNEL_MODES}")
        check_levels(self.levels, "ChannelConfig.levels")
        if not isinstance(self.num_elements, int) or self.num_elements < 1:
            raise _bad("num_elements", self.num_elements, "an integer >= 1")
        if self.code not in CHANNEL_CODES:
            raise _bad("code", self.code, f"one of {CHANNEL_CODES}")
        if (self.code in ("fitted", "remapped")) != bool(self.code_file):
            raise _bad(
                "code_file",
                self.code_file,
                "a fitted code's JSON file exactly when code is 'fitted' or 'remapped'",
            )
        if self.code_file:
            fitted = load_code(self.code_file)
            if (fitted.levels, fitted.elements) != (self.levels, self.num_elements):
                raise _bad(
                    "code_file",
                    self.code_file,
                    f"a code for levels {self.levels} and {self.num_elements} elements (it has "
                    f"levels {fitted.levels} and {fitted.elements} elements)",
                )
        if self.ecc not in ECC_NAMES:
            raise _bad("ecc", self.ecc, f"one of {ECC_NAMES}")
        if self.code == "permuted" and self.mode not in ("discrete", "reinforced"):
            raise _bad("code", self.code, f"not 'permuted' in mode {self.mode!r} (no symbols)")
        if self.code == "permuted" and self.ecc != "none":
            raise _bad("ecc", self.ecc, "'none' with code 'permuted' (its flips corrupt symbols)")
        if not (self.bit_cost >= 0 and self.bit_cost < float("inf")):
            raise _bad("bit_cost", self.bit_cost, "finite and >= 0")
        if not isinstance(self.link_gate, bool):
            raise _bad("link_gate", self.link_gate, "True or False")
        if self.on_silence not in ON_SILENCE:
            raise _bad("on_silence", self.on_silence, f"one of {ON_SILENCE}")
        for name, on in (("link_gate", self.link_gate), ("on_silence", self.holds)):
            if on and (self.mode != "discrete" or self.noise.delay):
                raise _bad(
                    name,
                    getattr(self, name),
                    f"{'False' if name == 'link_gate' else repr('null')} unless mode is "
                    f"'discrete' and noise.delay 0 (got mode {self.mode!r}, delay "
                    f"{self.noise.delay})",
                )
        if self.news_margin is not None and not (
            0 < self.news_margin <= 1 and self.link_gate and self.holds
        ):
            raise _bad(
                "news_margin",
                self.news_margin,
                "None, or in (0, 1] with link_gate True and on_silence 'hold' (got link_gate "
                f"{self.link_gate}, on_silence {self.on_silence!r})",
            )
        if self.prices not in PRICES:
            raise _bad("prices", self.prices, f"one of {PRICES}")
        if isinstance(self.check_bits, bool) or self.check_bits not in CHECK_BITS:
            raise _bad("check_bits", self.check_bits, f"one of {CHECK_BITS}")
        if self.prices == "wire" and (
            self.mode != "discrete" or self.code not in ("paper", "fixed") or self.ecc != "none"
        ):
            raise _bad(
                "prices",
                self.prices,
                "'payload' unless mode is 'discrete', code 'paper' or 'fixed' and ecc 'none' "
                f"(got mode {self.mode!r}, code {self.code!r}, ecc {self.ecc!r})",
            )

    # -- what the mode does: callers outside channel/ ask these, never compare ``mode`` --------

    @property
    def speaks(self) -> bool:
        """Links carry anything at all (every mode but ``off``)."""
        return self.mode != "off"

    @property
    def quantizes(self) -> bool:
        """Signals are quantized with a per-link dither that sender and receiver both draw from
        the shared key (``discrete``, the paper's)."""
        return self.mode == "discrete"

    @property
    def samples_symbols(self) -> bool:
        """Symbols are sampled as actions and learned by policy gradient, with no gradient
        across the channel (``reinforced``, RCL)."""
        return self.mode == "reinforced"

    @property
    def sends_symbols(self) -> bool:
        """Packets carry integer symbols in ``{0, ..., levels}`` (``discrete``, ``reinforced``)."""
        return self.quantizes or self.samples_symbols

    @property
    def sends_values(self) -> bool:
        """Packets carry the real-valued signal as float32 (``continuous``)."""
        return self.mode == "continuous"

    @property
    def prices_later(self) -> bool:
        """The rollout prices every step's links at once after its time loop instead of step
        by step inside it (``prices = "wire"``: the frame's price costs a few times less
        batched over the steps; the same values and gradients)."""
        return self.prices == "wire"

    @property
    def holds(self) -> bool:
        """A silent link delivers its last message, and receivers read which links are news
        (``on_silence = "hold"``)."""
        return self.on_silence == "hold"

    @property
    def lists_links(self) -> bool:
        """It can carry a routed team's live links listed by recipient (``channel.transmit``
        with ``senders``; docs/scaling.md): every link's cost is its own or a sum over its
        sender's frame, and it keeps no state per link (not ``reinforced``, not a ``fitted``
        code, not ``prices = "wire"``, not ``hold``, a clean channel)."""
        return (
            not self.samples_symbols
            and self.code != "fitted"
            and self.prices != "wire"
            and not self.holds
            and self.noise.clean
        )

    @property
    def signal_elements(self) -> int:
        """Elements of each link's signal ``z`` from the message head: the C message elements,
        and the link's gate (``link_gate``) last."""
        return self.num_elements + int(self.link_gate)

    @property
    def has_penalty(self) -> bool:
        """The channel has a differentiable bit penalty, so a lambda or a bit budget applies
        (``discrete``)."""
        return self.quantizes

    @property
    def deployable(self) -> bool:
        """A deployed agent can run it alone: its symbols need no draw but the dither
        (``discrete``, ``continuous``, ``off``; ``reinforced`` samples inside the channel) and
        its links are framed (``channel.frames``: not a ``fitted`` code, whose packets carry
        their own context)."""
        return not self.samples_symbols and self.code != "fitted"

    @property
    def code_obj(self) -> Code | FittedCode:
        if self.mode == "continuous":
            return Code("float32", self.levels)
        if self.code == "fitted":
            return load_code(self.code_file)
        if self.code == "permuted":
            return Code("paper", self.levels)  # payload: the paper's count
        if self.code == "remapped":
            counts = np.asarray(load_code(self.code_file).symbol_counts).sum(1)
            return Code("paper", self.levels, frequency_remap(counts))
        return Code(self.code, self.levels)

    def penalty(self, z: jax.Array) -> jax.Array:
        """The differentiable bit cost of each element of signals ``z`` (..., C): the paper's
        ``log2(levels z + 1)``, or for a learned (``remapped``) code the exact expected bits
        of its codewords (``channel.expected_bits``)."""
        return code_penalty(z, self.levels, self.code_obj)

    def link_penalty(
        self, z: jax.Array, code: Code | FittedCode | None = None, live=None
    ) -> jax.Array:
        """The differentiable cost of each link of signals ``z`` (..., L, C') -> (..., L), a
        sender's L links on the second-to-last axis, in the bits the channel prices
        (``prices``): the sum of :meth:`penalty` over the link's elements, with ``link_gate``
        (the gate ``g`` last in ``z``) times ``g``, the link's expected cost; or for ``wire``
        the sender's exact expected frame bits (``channel.expected_frame_bits``), shared
        equally by its links that exist (``live`` (..., L) bool; default all; a link that
        does not exist must have ``z = 0``). ``code``: price in this code instead of
        ``code_obj`` (the plug-in layer's)."""
        code = self.code_obj if code is None else code
        gate = None
        if self.link_gate:
            z, gate = z[..., :-1], z[..., -1]
        if self.prices == "wire":
            lengths = code.wire_lengths(z.shape[-1])
            frame = expected_frame_bits(z, self.levels, lengths, self.check_bits, gate)
            if live is None:
                return jnp.broadcast_to(frame[..., None] / z.shape[-2], z.shape[:-1])
            count = jnp.maximum(live.sum(-1, keepdims=True), 1)
            return jnp.where(live, frame[..., None] / count, 0.0)
        cost = code_penalty(z, self.levels, code).sum(-1)
        return cost if gate is None else gate * cost

    def max_bits_per_step(self, num_agents: int) -> int:
        """The most bits (in the count of ``prices``) a team of ``num_agents`` can send in one
        step: every element of every link at the code's longest codeword, and for ``wire``
        each sender's whole frame."""
        code = self.code_obj
        if code.name == "fitted":
            code = Code("paper", self.levels)  # payload: the paper's count
        links = num_agents - 1
        if self.prices == "wire":
            longest = int(code.wire_lengths(self.num_elements).max())
            body = links * (1 + self.num_elements * (1 + longest))
            return num_agents * (8 * (-(-body // 8)) + self.check_bits)
        per_element = code.max_paper_length if code.name == "paper" else code.fixed_width
        return num_agents * links * self.num_elements * per_element

    @property
    def link_rules(self) -> dict:
        """The link rules' settings by field name (``link_gate``, ``on_silence``,
        ``news_margin``), for tables that say which channel a row ran on."""
        return {n: getattr(self, n) for n in ("link_gate", "on_silence", "news_margin")}

    @property
    def opens_on_news(self) -> bool:
        """A link's gate also opens when what it would say differs from what its recipient
        holds (``news_margin``): the price of a gate is not the head's alone."""
        return self.news_margin is not None

    def team_checks(self, reads_sent: bool, aggregate: str) -> dict[str, tuple[bool, str]]:
        """What a team's agent settings need of this channel, as a learner config's checks
        (``field: (ok, allowed)``): reading back what its links sent needs silence that holds,
        and the news inputs of ``hold`` the ``concat`` inbox."""
        return {
            "agent.reads_sent": (
                not reads_sent or self.holds,
                "False unless channel.on_silence is 'hold'",
            ),
            "agent.aggregate": (
                not self.holds or aggregate == "concat",
                "'concat' with channel.on_silence 'hold' (its news inputs are per link)",
            ),
        }

    @property
    def counted_metric(self) -> str:
        """The logged metric of the bits the channel prices: ``bits_per_step`` (payload) or
        ``wire_bits_per_step``."""
        return "wire_bits_per_step" if self.prices == "wire" else "bits_per_step"


@functools.lru_cache(maxsize=8)
def _load_code(path: str, mtime_ns: int, size: int) -> FittedCode:
    return FittedCode.from_json(Path(path).read_text())


def load_code(path: str) -> FittedCode:
    """The fitted code in the JSON file ``path`` (read once while the file is unchanged)."""
    try:
        st = os.stat(path)
    except OSError as e:
        raise _bad("code_file", path, f"a readable fitted-code JSON file ({e.strerror})") from None
    try:
        return _load_code(str(path), st.st_mtime_ns, st.st_size)
    except ValueError as e:
        raise _bad("code_file", path, f"a valid fitted-code JSON file ({e})") from None


def _bad(name: str, value, allowed: str) -> ValueError:
    return ValueError(f"ChannelConfig.{name} must be {allowed}, got {value!r}")
