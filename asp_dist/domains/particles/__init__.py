"""The particle speaker–listener world of the paper (§ Particle World), trained with A2C.

An actor moves in the box [-5, 5]² by one unit per step (stay, ±x, ±y, clipped to the box).
A speaker sees the actor's (x, y) and emits a continuous message; the listener (the actor)
sees only the message and picks an action from a softmax over the five moves. The target is
fixed for a whole trial and never observed: the pair learns where it is from the reward,
10 per step within 1.4 units of the target, else 1/distance, shared by both agents.
Episodes last 40 steps; the actor re-spawns uniformly in the box at every episode start.

Self-play is synchronous A2C over a batch of environments advanced `particles_rollout_len`
steps per update, with n-step bootstrapped returns from a critic that sees the position and
the time left (episodes are truncated at a fixed length, so time is part of the state and the
last step is a true terminal). The message is differentiable: the listener's policy-gradient
loss flows back through it into the speaker.

Everything is vectorised over environments; the only Python loops run over time steps.
The new agents train with hand-derived gradients (asp_dist/domains/particles/packed.py, a single
cell as a pack of one); the autograd functions here (a2c_update, paired_loss) are the reference
that trainer is tested against, and train the base and the cells it does not implement.

Choices the paper leaves open (measurements in docs/decisions/0007-particle-world.md): the target
is drawn in [-4, 4]² (the ≥ 300 bar is reachable from everywhere there); the reward is paid for
the position after the move; actions are sampled from the listener's softmax in evaluation as
in training; the new agents' batch of 8 is 8 staggered envs advanced one step per update
(8 transitions, 8 messages for the discriminator, as the paper's batches of 8 from a replay
buffer); the base uses 256 envs.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from asp_dist.core.contract import GameDomain, MetricInfo, PaperFacts, game_attribute, require
from asp_dist.knobs import Knob

if TYPE_CHECKING:
    from asp_dist.spec import CellSpec

POOL = 4096  # paired tuples are the first n of a fixed pool of base episodes


class ParticlesDomain(GameDomain):
    name = "particles"
    channels = ("message",)
    accept_field = "particles_accept_return"
    paper = PaperFacts(
        metric_label="mixed-team reward per 40-step episode",
        claim="ASP better than OSP and PC over 2–4 paired (Friedman, p < 0.01 each)",
        test_paired=(2, 4),
    )
    optimizer_options = {"fused": True}  # 12 small tensors: fused Adam is ~3-4x faster per step on CPU
    knobs = (  # name, type, default, doc; choices, neutral value, base-shaping, bound
        Knob('particles_message_dim', int, 128, "Dimension of the speaker's continuous message (paper: 128).",
             bound=16_384),
        Knob('particles_hidden', int, 64, 'Hidden units of speaker, listener and critic MLPs.', bound=16_384),
        Knob('particles_episode_len', int, 40, 'Steps per episode (paper: 40).', bound=100_000),
        Knob('particles_gamma', float, 0.95, 'A2C discount factor.'),
        Knob('particles_entropy', float, 0.01, 'A2C entropy bonus weight.'),
        Knob('particles_value_coef', float, 0.5, 'A2C value-loss weight.'),
        Knob('particles_rollout_len', int, 1, 'Environment steps per A2C update (n-step return length).',
             bound=10_000),
        Knob('particles_base_envs', int, 256, 'Parallel environments used to train the base pair.', bound=1_000_000),
        Knob('particles_base_lr', float, 0.003, 'Adam learning rate of the base pair.'),
        Knob('particles_accept_return', float, 300.0, 'Base accepted at mean self-play return >= this (paper: 300).'),
        Knob('particles_replay_size', int, 0,
             "0: on-policy A2C on the current rollout. N > 0: the paper's replay buffer — each update adds "
             'batch_size fresh transitions to a FIFO of the last N and trains (and shows the discriminator) a '
             'uniform batch of it.', neutral=0, shapes_base=False, bound=10_000_000, optional=False),
        Knob('particles_paired_listener', bool, True,
             "Paired loss adds the listener's cross-entropy on the base's (message, action); false: speaker MSE "
             'only, as the paper states.', neutral=True, shapes_base=False, optional=False),
    )
    legacy_identity = True  # knobs recorded as CellSpec fields before domains were plugins
    protocol_defaults = dict(lambda_unpaired_schedule="constant", lambda_schedule_frac=0.5, base_steps_growth=1.0,
                             base_max_attempts=5)  # before the reproduction study changed them
    # A cell in about a second (asp-dist check-domain, the registry-wide tests)
    smoke = dict(train_steps=40, base_train_steps=30, particles_base_envs=32, eval_episodes=64, unpaired_size=256,
                 particles_hidden=16, particles_message_dim=16, particles_accept_return=0.0)
    defaults = dict(
        lambda_paired=1.0, lambda_unpaired=0.1, unpaired_size=4096,
        train_steps=25000, batch_size=8, lr=1e-3,
        disc_hidden=64, disc_layers=1, disc_lr=1e-3,
        base_train_steps=3000, eval_episodes=1000,
        # Chosen by the reproduction study (docs/reproduction.md,
        # docs/decisions/0021-domain-defaults-from-reproduction-study.md): λ1 warms up over
        # the first half so self-play settles before the adversary pulls, and a base that misses the
        # bar is retried with a growing budget (1.5^k) up to 10 times, so that a trial does not lose its
        # cells to unlucky seeds (every trial of the confirmatory run and the paper grid got a base).
        lambda_unpaired_schedule="warmup", lambda_schedule_frac=0.5,
        base_steps_growth=1.5, base_max_attempts=10,
    )
    metrics = {
        "mixed": MetricInfo(True, "Eq. 1: mean episode return of the two mixed pairs"),
        "mixed_base_speaker": MetricInfo(True, "mean episode return of base speaker + new listener"),
        "mixed_new_speaker": MetricInfo(True, "mean episode return of new speaker + base listener"),
        "self_play_new": MetricInfo(True, "mean episode return of the new pair"),
        "self_play_base": MetricInfo(True, "mean episode return of the base pair"),
        "message_mse": MetricInfo(False, "MSE between new and base speaker messages on uniform states"),
        "action_match": MetricInfo(True, "fraction of base messages (uniform states) on which the new "
                                         "listener's greedy action equals the base listener's"),
    }

    def validate(self, spec: CellSpec) -> None:
        for name in ("particles_message_dim", "particles_hidden", "particles_episode_len",
                     "particles_rollout_len", "particles_base_envs"):
            require(getattr(spec, name) >= 1, f"{name} must be >= 1, got {getattr(spec, name)}")
        require(0.0 <= spec.particles_gamma <= 1.0, f"particles_gamma must be in [0, 1], got {spec.particles_gamma}")
        require(spec.particles_base_lr > 0, f"particles_base_lr must be > 0, got {spec.particles_base_lr}")
        require(spec.paired <= POOL, f"paired must be <= {POOL} for particles, got {spec.paired}")


    def tensor_sizes(self, spec: CellSpec) -> dict[str, int]:
        width = max(spec.particles_message_dim, spec.particles_hidden)
        return {"particles_message_dim × particles_hidden": spec.particles_message_dim * spec.particles_hidden,
                "particles_rollout_len × particles_base_envs × width":
                    spec.particles_rollout_len * spec.particles_base_envs * width,
                "particles_rollout_len × batch_size × width": spec.particles_rollout_len * spec.batch_size * width,
                "eval_episodes × width": spec.eval_episodes * width, f"{POOL} paired episodes × width": POOL * width}

    def channel_dims(self, spec: CellSpec) -> dict[str, int]:
        return {"message": spec.particles_message_dim}


def __getattr__(name: str) -> Any:
    """The game's names (ParticleAgents, a2c_update, env_step, BOX, ...), imported on first access."""
    return game_attribute(__name__, name)
