"""The one-step signaling game of the paper's policy-space analysis.

S states (uniformly likely) fall into A classes whose sizes follow a token distribution p
(p_k ∝ exp(-skew·k): skew 0 is uniform, larger is more concentrated). A speaker sees the state
and sends one of A tokens; a listener sees only the token and must name the state's class
(reward 1 if right). Self-play is satisfied by any bijection between classes and tokens, so
there are A! equally good conventions; the base uses one chosen at random per trial.

An adversary that matches the base's token marginal prunes the conventions whose token
frequencies differ from the base's — none when p is uniform, all but one when the class
sizes are all distinct. The game is exact and tiny: a cell runs in about a second, so tests,
CI and the smoke sweep lean on it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from asp_dist.core.contract import GameDomain, MetricInfo, PaperFacts, game_attribute, require
from asp_dist.knobs import Knob

if TYPE_CHECKING:
    from asp_dist.spec import CellSpec


class SignalingDomain(GameDomain):
    name = "signaling"
    default_for_specs = True  # CellSpec(...) without a domain is a signaling cell (as before domains were plugins)
    channels = ("token",)
    accept_field = None
    paper = PaperFacts(
        metric_label="mixed-team accuracy (fraction of states)",
        claim="(policy-space analysis) ASP prunes more conventions, so helps more, the more skewed the tokens",
        knob_labels={"signaling_skew": "token skew (0 = uniform)"},
    )
    knobs = (  # name, type, default, doc; choices, neutral value, base-shaping, bound
        Knob('signaling_states', int, 32, 'S: number of states of the one-step signaling game.', bound=1_000_000),
        Knob('signaling_tokens', int, 4, 'A: number of tokens (and listener actions).', bound=10_000),
        Knob('signaling_skew', float, 1.0,
             'Token-distribution skew: 0 = uniform, larger = more concentrated (p_k ∝ exp(-skew·k)).'),
    )
    legacy_identity = True  # knobs recorded as CellSpec fields before domains were plugins
    # A cell in about a second (asp-dist check-domain, the registry-wide tests)
    smoke = dict(train_steps=60, batch_size=16, unpaired_size=128)
    defaults = dict(
        lambda_paired=1.0, lambda_unpaired=1.0, unpaired_size=1024,
        train_steps=300, batch_size=256, lr=0.05,
        disc_hidden=32, disc_layers=1, disc_lr=0.01,
        base_train_steps=0, eval_episodes=1,
    )
    metrics = {
        "mixed": MetricInfo(True, "Eq. 1: mean of the two mixed pairs' accuracy"),
        "mixed_base_speaker": MetricInfo(True, "accuracy of base speaker + new listener"),
        "mixed_new_speaker": MetricInfo(True, "accuracy of new speaker + base listener"),
        "self_play_new": MetricInfo(True, "accuracy of the new pair"),
        "self_play_base": MetricInfo(True, "accuracy of the base pair"),
        "convention_match": MetricInfo(True, "fraction of states where the new speaker sends the base's token"),
    }

    def validate(self, spec: CellSpec) -> None:
        require(spec.signaling_tokens >= 2, "signaling_tokens must be >= 2")
        require(spec.signaling_states >= spec.signaling_tokens,
                f"signaling_states ({spec.signaling_states}) must be >= signaling_tokens ({spec.signaling_tokens})")

    def tensor_sizes(self, spec: CellSpec) -> dict[str, int]:
        A = spec.signaling_tokens
        return {"signaling_states × signaling_tokens": spec.signaling_states * A,
                "batch_size × signaling_tokens": spec.batch_size * A, "paired × signaling_tokens": spec.paired * A}

    def channel_dims(self, spec: CellSpec) -> dict[str, int]:
        return {"token": spec.signaling_tokens}


def __getattr__(name: str) -> Any:
    """The game's names (SignalingAgents, class_sizes, state_classes, ...), imported on first access."""
    return game_attribute(__name__, name)
