"""The Lewis referential game, as emergent-communication research plays it: an asp-dist domain plugin.

An object has A attributes with V values each (V^A objects). A speaker sees a target object and
sends a message of L symbols from a vocabulary of K; a listener sees the message and C candidates
(the target and C-1 distinct distractors drawn uniformly among the other objects, in random
order) and picks one. Both are rewarded when it picks the target: the score is the listener's
accuracy. The base pair learns a code (object -> message) in self-play; that code is the
convention a new pair must adopt from a few paired (object, base message) examples, and — for
ASP — from unpaired base messages with no objects (the channel "message").

This module is the card (no torch import): knobs, defaults, metrics, what the paper says (nothing:
the game is not in it), validation. The torch half is asp_referential.game.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from asp_dist.core.contract import GameDomain, MetricInfo, PaperFacts, game_attribute, require
from asp_dist.knobs import Knob

if TYPE_CHECKING:
    from asp_dist.spec import CellSpec

__version__ = "0.1.0"

POOL = 4096  # paired games are the first n of a fixed pool of POOL base games, so P(n) is a prefix of P(n+1)


class ReferentialDomain(GameDomain):
    name = "referential"
    channels = ("message",)
    accept_field = "referential_accept_accuracy"
    paper = PaperFacts(
        metric_label="mixed-team accuracy (fraction of games won)",
        claim="does ASP help a new pair adopt the base pair's referential code?", in_paper=False,
        knob_labels={"referential_vocab": "vocabulary size K", "referential_msg_len": "message length L",
                     "referential_candidates": "candidates C"},
    )
    knobs = (  # name, type, default, doc; choices, neutral value, base-shaping, bound
        Knob("referential_attributes", int, 3, "A: attributes of an object.", bound=16),
        Knob("referential_values", int, 4, "V: values of each attribute (V^A objects).", bound=1024),
        Knob("referential_msg_len", int, 2, "L: symbols per message.", bound=64),
        Knob("referential_vocab", int, 10, "K: vocabulary size (K^L messages).", bound=4096),
        Knob("referential_candidates", int, 5, "C: candidates the listener sees (target + C-1 distractors).",
             bound=4096),
        Knob("referential_hidden", int, 64, "Hidden units of the speaker's and listener's MLPs.", bound=16_384),
        Knob("referential_tau", float, 1.0, "Gumbel-softmax temperature of the straight-through symbols."),
        Knob("referential_base_batch", int, 128, "Games per update when the base pair trains.", bound=1_000_000),
        Knob("referential_base_lr", float, 0.003, "Adam learning rate of the base pair."),
        Knob("referential_accept_accuracy", float, 0.9,
             "Base accepted at greedy self-play accuracy >= this (on 4096 games); retrained otherwise."),
    )
    # A cell in about a second (asp-dist check-domain, the registry-wide tests)
    smoke = dict(train_steps=60, base_train_steps=100, batch_size=32, eval_episodes=256, unpaired_size=128,
                 referential_hidden=16, referential_accept_accuracy=0.0)
    defaults = dict(
        lambda_paired=1.0, lambda_unpaired=0.1, unpaired_size=1024,
        train_steps=5000, batch_size=64, lr=0.003,
        disc_hidden=64, disc_layers=1, disc_lr=0.001,
        base_train_steps=1000, eval_episodes=2000,
        base_steps_growth=1.5,
    )
    metrics = {
        "mixed": MetricInfo(True, "Eq. 1: mean accuracy of (base speaker + new listener) and (new speaker + base listener)"),
        "mixed_base_speaker": MetricInfo(True, "accuracy of base speaker + new listener"),
        "mixed_new_speaker": MetricInfo(True, "accuracy of new speaker + base listener"),
        "self_play_new": MetricInfo(True, "accuracy of the new pair"),
        "self_play_base": MetricInfo(True, "accuracy of the base pair"),
        "message_match": MetricInfo(True, "fraction of all objects on which the new speaker's greedy message "
                                          "equals the base's"),
    }

    def validate(self, spec: CellSpec) -> None:
        for name in ("referential_attributes", "referential_msg_len", "referential_hidden",
                     "referential_base_batch"):
            require(getattr(spec, name) >= 1, f"{name} must be >= 1, got {getattr(spec, name)}")
        for name in ("referential_values", "referential_vocab", "referential_candidates"):
            require(getattr(spec, name) >= 2, f"{name} must be >= 2, got {getattr(spec, name)}")
        objects = spec.referential_values ** spec.referential_attributes
        require(objects <= 1_000_000, f"referential_values ** referential_attributes (objects) must be <= 1000000, "
                                      f"got {objects}")
        require(spec.referential_candidates <= objects,
                f"referential_candidates ({spec.referential_candidates}) must be <= the number of objects "
                f"(referential_values ** referential_attributes = {objects})")
        require(spec.referential_tau > 0, f"referential_tau must be > 0, got {spec.referential_tau}")
        require(spec.referential_base_lr > 0, f"referential_base_lr must be > 0, got {spec.referential_base_lr}")
        require(spec.paired <= POOL, f"paired must be <= {POOL} for referential, got {spec.paired}")

    def tensor_sizes(self, spec: CellSpec) -> dict[str, int]:
        objects = spec.referential_values ** spec.referential_attributes
        games = max(POOL, spec.eval_episodes, spec.batch_size, spec.referential_base_batch)
        feat = spec.referential_attributes * spec.referential_values
        msg = spec.referential_msg_len * spec.referential_vocab
        H = spec.referential_hidden
        return {"games × objects (distractor draw)": games * objects,
                "games × candidates × hidden": games * spec.referential_candidates * H,
                "objects × A·V": objects * feat, "hidden × L·K": H * msg, "hidden × A·V": H * feat}

    def channel_dims(self, spec: CellSpec) -> dict[str, int]:
        return {"message": spec.referential_msg_len * spec.referential_vocab}


def __getattr__(name: str) -> Any:
    """The game's names (ReferentialAgents, sample_games, ...), imported on first access."""
    return game_attribute(__name__, name)
