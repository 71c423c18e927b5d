"""The field's peers beside asp-dist on MPE's speaker–listener game, in one process pinned to one core.

    bash bench/peers-venv.sh                                      # once: .venv-peers/, the peers' own venv
    .venv-peers/bin/python bench/peers.py --quick                 # the plumbing end to end (< 60 CPU-s)
    .venv-peers/bin/python bench/peers.py --json bench/results/peers.json   # the measurement (see the notes)

Two parts, every figure in CPU seconds of this process (time.process_time), wall seconds beside:

  race       CPU-seconds each trainer spends until its speaker–listener team's words carry the goal:
               mappo, ippo  BenchMARL's MAPPO / IPPO on its VMAS task simple_speaker_listener (VMAS's own
                            scenario, 100-step episodes), BenchMARL's defaults for the task, discrete actions
               asp          asp-dist's base trainer (asp_dist.domains.vmas.game.train_base's loop: episodes of
                            256 worlds through the differentiable world, Adam 0.003) at the vmas_speaker_listener
                            defaults, in asp-dist's world (mpe2's on VMAS's simulator, 25-step episodes)
               asp-pack     --pack-teams such teams trained as one pack by asp-dist's packed trainer (OSP members
                            without paired data: pure self-play at the base's settings); its figure is the pack's
                            CPU / K, when every team meets the bar
             One judge (`judge` below) looks at every team after --check-cpu-s of training CPU, then after every
             --check-growth more (its own CPU not counted), in the world that team trained in, with the same
             code: MI goal → sampled word over every step of --eval-worlds worlds (a third per goal) on one
             reset seed, and the drop in −distance² of the listener to the goal, per 25 steps, when every word
             is replaced by a uniformly random one (same seeds, same action draws). Bar: MI >= 0.9 nats and
             drop >= 3 (asp-dist's accept_mi and accept_drop). A trainer stops at the bar or when
             --budget-cpu-s is spent; one that never meets it is reported with its best MI and drop.
  env steps  world-steps per CPU-second with random actions, no learning: JaxMARL's jitted, vmapped MPE
             simple_speaker_listener (a 25-step lax.scan per call, and one jitted step per call; compile CPU
             apart), VMAS (asp-dist's Worlds, as bench/bench_vmas.py; and VMAS's own scenario through its
             Environment.step, BenchMARL's world) and mpe2's copies (only where the pettingzoo extra is
             installed), at --batches worlds.

One core: the process pins itself to one core before torch or jax load (XLA sizes its thread pool from the
affinity; its XLA_FLAGS alone left jax 0.10 on two threads), OMP_NUM_THREADS=1, torch.set_num_threads(1).
Why each choice (worlds, episode lengths, the drop's units, BenchMARL's settings): the docstrings of judge,
AspWorld, VmasWorld and race_benchmarl.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import json
import logging
import math
import os
import sys
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import (  # noqa: E402  (standard library only at import: before torch and jax)
    cpu_per_call,
    machine_info,
    mpe2_random_steps_per_cpu_s,
    vmas_random_steps_per_cpu_s,
)

BAR_MI, BAR_DROP, DROP_STEPS = 0.9, 3.0, 25  # asp-dist's accept_mi / accept_drop; the drop is per 25 steps
WORDS = 3
PEERS = ("mappo", "ippo", "asp", "asp-pack", "steps")
NEEDED = ("torch", "benchmarl", "torchrl", "tensordict", "vmas", "jax", "jaxmarl", "asp_dist")


# ---- flags ---------------------------------------------------------------------------------------------------
class Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line and exit 2, as asp-dist's own commands
        sys.stderr.write(f"peers.py: error: {message}\n")
        sys.exit(2)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = Parser(prog="peers.py", description=__doc__.splitlines()[0])
    p.add_argument("--budget-cpu-s", type=float, default=1800.0,
                   help="training CPU-seconds each trainer may spend; one that has not reached the bar by then is "
                        "reported with its best MI and drop (default 1800)")
    p.add_argument("--check-cpu-s", type=float, default=2.0,
                   help="the judge first looks at a team after this many training CPU-seconds, then after every "
                        "--check-growth more, at least this far apart, each time at the first update past it "
                        "(default 2)")
    p.add_argument("--check-growth", type=float, default=0.1,
                   help="look again after this fraction more training CPU: the CPU-seconds to the bar are known to "
                        "within it (or one update, if longer) for every trainer alike (default 0.1)")
    p.add_argument("--eval-worlds", type=int, default=512,
                   help="worlds per judgement, rounded up to a multiple of 3 (a third per goal; default 512 -> 513)")
    p.add_argument("--eval-seed", type=int, default=20261208, help="the judge's reset seed (its action seed: +1)")
    p.add_argument("--seed", type=int, default=0,
                   help="BenchMARL's experiment seed and asp-dist's trial (its base seed: seed_for('base'))")
    p.add_argument("--peers", default=",".join(PEERS), help=f"comma-separated subset of {','.join(PEERS)}")
    p.add_argument("--batches", default=None, help="worlds per step in the env-steps part (default 1,64,1024; "
                   "--quick: 1,64, as each batch size costs jax a compile of 6-10 CPU-s)")
    p.add_argument("--pack-teams", type=int, default=8,
                   help="asp-pack: teams trained as one pack (its budget and first check scale with it; default 8)")
    p.add_argument("--core", type=int, default=None, help="core to pin to (default: the lowest this process may use)")
    p.add_argument("--json", type=Path, help="also write every figure here")
    p.add_argument("--quick", action="store_true",
                   help="plumbing only: 5 CPU-s per trainer, small BenchMARL batches, 24 judged worlds, short timings")
    args = p.parse_args(argv)
    args.peers = [x.strip() for x in args.peers.split(",") if x.strip()]
    unknown = [x for x in args.peers if x not in PEERS]
    if unknown or not args.peers:
        p.error(f"--peers: unknown {','.join(unknown) or '(none given)'}; choose from {','.join(PEERS)}")
    if args.batches is None:
        args.batches = "1,64" if args.quick else "1,64,1024"
    try:
        args.batches = [int(x) for x in args.batches.split(",")]
    except ValueError:
        p.error(f"--batches: comma-separated integers, got {args.batches!r}")
    if min(args.batches) < 1:
        p.error("--batches: every batch must be >= 1")
    for name in ("budget_cpu_s", "check_cpu_s", "check_growth"):
        if not getattr(args, name) > 0:
            p.error(f"--{name.replace('_', '-')} must be > 0, got {getattr(args, name)}")
    if args.pack_teams < 1:
        p.error(f"--pack-teams must be >= 1, got {args.pack_teams}")
    if args.eval_worlds < 3:
        p.error(f"--eval-worlds must be >= 3, got {args.eval_worlds}")
    if args.json is not None:  # refused now, not after an hour of measuring: open it (and remove it if new)
        existed = args.json.exists()
        try:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            with open(args.json, "a"):
                pass
        except OSError as err:
            p.error(f"--json {args.json}: cannot be written ({err.strerror or err})")
        if not existed:
            args.json.unlink()
    cores = sorted(os.sched_getaffinity(0))
    if args.core is None:
        args.core = cores[0]
    elif args.core not in cores:
        p.error(f"--core {args.core} is not one this process may use ({cores})")
    if args.quick:
        args.budget_cpu_s, args.check_cpu_s, args.eval_worlds = min(args.budget_cpu_s, 5.0), 2.0, 24
    args.eval_worlds = 3 * math.ceil(args.eval_worlds / 3)
    missing = [m for m in NEEDED if importlib.util.find_spec(m) is None]
    if missing:
        p.error(f"{', '.join(missing)} not installed in {sys.executable}: run bash bench/peers-venv.sh, then "
                f".venv-peers/bin/python bench/peers.py")
    return args


def one_core(core: int) -> None:
    """Pin this process to one core and ask every library for one thread, before torch or jax load."""
    os.sched_setaffinity(0, {core})
    os.environ.update(OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", JAX_PLATFORMS="cpu",
                      XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1",
                      TQDM_DISABLE="1")  # BenchMARL's progress bar


# ---- the judge: one metric for every team, in the world it trained in ---------------------------------------
def judge(world, speak: Callable, move: Callable, seed: int) -> dict[str, float]:
    """Play world.n worlds for world.steps steps from reset seed `seed`, twice: with the team's words and with
    every word replaced by a uniformly random one. speak(speaker_obs, gen) -> (n,) word, move(listener_obs, gen)
    -> (n,) move index, each sampled from the team's policy. Separate generators for the speaker, the listener and
    the random words, so both plays draw the listener's moves alike (common random numbers).

    mi: goal → sampled word over every step of every world (asp-dist's word_mi; the goals a third each, so a
    perfect code scores log 3 = 1.10 in every world). drop: the listener's summed −distance² to its goal, team
    words minus random words, per 25 steps. One unit for both worlds: −distance² is mpe2's reward and asp-dist's
    world's own, and per 25 steps is per asp-dist episode, the unit of its accept_drop; VMAS's 100-step episodes
    count a quarter. (A hand-written team, speaker saying the goal, listener heading for the named landmark,
    drops 10.8 in asp-dist's world and 12.4 in VMAS's by this measure, so the bar of 3 asks about as much of
    both.) drop_own: the same difference in the world's own reward per episode (VMAS's: −2·distance, 100
    steps), reported beside it."""
    import torch

    from asp_dist.domains.vmas.game import word_mi

    plays = {}
    with torch.no_grad():
        for random_words in (False, True):
            g_speak, g_move, g_word = (torch.Generator().manual_seed(seed + 1 + k) for k in range(3))
            obs = world.reset(seed)
            said, own, dist2 = [], torch.zeros(world.n), torch.zeros(world.n)
            for _ in range(world.steps):
                word = speak(obs[0], g_speak)
                if random_words:
                    word = torch.randint(WORDS, (world.n,), generator=g_word)
                obs, reward, square = world.step(word, move(obs[1], g_move))
                said.append(word)
                own, dist2 = own + reward, dist2 - square
            plays[random_words] = torch.stack(said), float(own.mean()), float(dist2.mean())
    scale = DROP_STEPS / world.steps
    (words, own, dist2), (_, own_random, dist2_random) = plays[False], plays[True]
    return {"mi": word_mi(world.goal, words), "drop": (dist2 - dist2_random) * scale, "drop_own": own - own_random,
            "return_dist2_per25": dist2 * scale, "return_own": own}


def meets_bar(fig: dict[str, float]) -> bool:
    return fig["mi"] >= BAR_MI and fig["drop"] >= BAR_DROP


class AspWorld:
    """asp-dist's world (mpe2's speaker–listener on VMAS's simulator: asp_dist/domains/vmas/world.py) at the
    domain's defaults: 25 steps, −distance² reward, 5 moves, 3 words."""

    def __init__(self, spec, n: int):
        import torch

        from asp_dist.domains.vmas import game
        from asp_dist.domains.vmas.world import Worlds

        self.worlds, self.n, self.steps = Worlds(n, game.options(spec)), n, game.knob(spec, "episode_len")
        self.goal = torch.arange(n) % 3

    def reset(self, seed: int):
        worlds = self.worlds
        worlds.reset(seed)
        scenario = worlds.env.scenario
        # a third of the worlds per goal, as on the VMAS side (which can only set one goal per batch)
        scenario.goal = self.goal.view(-1, 1).clone()
        worlds.obs = [scenario.observation(agent) for agent in worlds.env.world.agents]
        return worlds.obs

    def step(self, word, move):
        import torch.nn.functional as F

        reward = self.worlds.step([{"say": F.one_hot(word, WORDS).float()}, {"move": F.one_hot(move, 5).float()}])
        scenario = self.worlds.env.scenario
        square = (self.worlds.env.world.agents[1].state.pos - scenario.goal_position(0)).pow(2).sum(-1)
        return self.worlds.obs, reward, square


class VmasWorld:
    """VMAS's own simple_speaker_listener, BenchMARL's task (speaker: 27 actions = 9 moves × 3 words, the word is
    action % 3; listener: 9 moves of force 1; reward −2·distance; `steps` steps, the task's max_steps). VMAS draws
    one goal for a whole batch at a reset, so the n worlds are three batches, one per goal, set after the reset.
    A world's dynamics, observations and reward depend on its own goal only, so these are the worlds BenchMARL
    trains in, their goals balanced instead of drawn once per batch."""

    def __init__(self, n: int, steps: int):
        import torch
        import vmas

        self.n, self.k, self.steps = n, n // 3, steps
        self.envs = [vmas.make_env("simple_speaker_listener", num_envs=self.k, device="cpu", continuous_actions=False,
                                   seed=0) for _ in range(3)]
        self.goal = torch.arange(3).repeat_interleave(self.k)

    def reset(self, seed: int):
        import torch

        obs = []
        for g, env in enumerate(self.envs):
            env.reset(seed=seed + g)  # VMAS seeds its global RNG inside, restoring the caller's after
            scenario = env.scenario
            scenario.world.agents[0].goal_b = scenario.world.landmarks[g]  # what the speaker sees and the reward uses
            obs.append([scenario.observation(agent) for agent in env.agents])
        return [torch.cat([o[i] for o in obs]) for i in range(2)]

    def step(self, word, move):
        import torch

        obs, rewards, squares = [], [], []
        for g, env in enumerate(self.envs):
            part = slice(g * self.k, (g + 1) * self.k)
            # the speaker's flat action with its (ignored: it cannot move) move parts 0: the word itself
            o, r, _, _ = env.step([word[part].unsqueeze(-1), move[part].unsqueeze(-1)])
            a = env.scenario.world.agents[0]
            obs.append(o)
            rewards.append(r[0])
            squares.append((a.goal_a.state.pos - a.goal_b.state.pos).pow(2).sum(-1))
        return [torch.cat([o[i] for o in obs]) for i in range(2)], torch.cat(rewards), torch.cat(squares)


def sampler(logits_of: Callable, modulo: int | None = None) -> Callable:
    """A team member as the judge calls it: observations, generator -> one sampled index per row."""
    import torch

    def sample(obs, gen):
        index = torch.multinomial(logits_of(obs).softmax(-1), 1, generator=gen).view(-1)
        return index % modulo if modulo else index

    return sample


# ---- the race: a clock that leaves the judge's CPU out ------------------------------------------------------
class Stop(Exception):
    """Raised from BenchMARL's callback to end its experiment at the bar or the budget."""


class Race:
    """One trainer's clock and its checks: training CPU leaves the judge's own CPU out; the judge looks after
    `first` CPU-seconds, then after every `growth` more (at least `first` apart). `done(figures)`: whether the
    trainer has reached its goal (default: its team meets the bar); `now`: the training CPU of the current check."""

    def __init__(self, name: str, look: Callable[[], dict], budget: float, first: float, growth: float,
                 done: Callable[[dict], bool] = meets_bar):
        self.name, self.look, self.budget, self.first, self.growth = name, look, budget, first, growth
        self.done = done
        self.checks: list[dict] = []
        self.reached = False
        self.now = 0.0

    def start(self) -> None:
        self.cpu0, self.wall0, self.judge_cpu, self.judge_wall, self.next = (time.process_time(), time.perf_counter(),
                                                                             0.0, 0.0, self.first)

    def train_cpu(self) -> float:
        return time.process_time() - self.cpu0 - self.judge_cpu

    def update(self, world_steps: int) -> bool:
        """After each update: judge when a check is due; True when the trainer must stop (bar or budget)."""
        cpu, wall = self.train_cpu(), time.perf_counter() - self.wall0 - self.judge_wall
        spent = cpu >= self.budget
        if cpu < self.next and not spent:
            return False
        self.next = max(cpu + self.first, cpu * (1 + self.growth))
        self.now = cpu
        c0, w0 = time.process_time(), time.perf_counter()
        fig = self.look()
        self.judge_cpu += time.process_time() - c0
        self.judge_wall += time.perf_counter() - w0
        fig.update(train_cpu_s=cpu, train_wall_s=wall, world_steps=world_steps)
        self.checks.append(fig)
        self.reached = self.done(fig)
        print(f"  {self.name:6s} {cpu:8.1f} CPU-s {world_steps:13,d} world-steps   MI {fig['mi']:.3f}   "
              f"drop {fig['drop']:6.2f} /25 steps (own reward {fig['drop_own']:7.2f} /episode)"
              f"{'   bar met' if self.reached else ''}", flush=True)
        return self.reached or spent

    def summary(self, **extra) -> dict[str, Any]:
        last = self.checks[-1]
        return {"reached": self.reached, "train_cpu_s": last["train_cpu_s"], "train_wall_s": last["train_wall_s"],
                "world_steps": last["world_steps"], "mi": last["mi"], "drop": last["drop"],
                "best_mi": max(c["mi"] for c in self.checks), "best_drop": max(c["drop"] for c in self.checks),
                "judge_cpu_s": self.judge_cpu, "checks": self.checks, **extra}


# ---- the trainers ------------------------------------------------------------------------------------------
def race_benchmarl(algorithm: str, args) -> dict[str, Any]:
    """BenchMARL's MAPPO or IPPO on its VMAS simple_speaker_listener task at BenchMARL's defaults
    (base_experiment.yaml, mappo/ippo.yaml, layers/mlp.yaml, the task's max_steps 100), on CPU, except:
    discrete actions (prefer_continuous_actions False: words as symbols, as in MPE; continuous
    actions would make the word a real vector in [0,1]^3), nothing logged, checkpointed or evaluated by
    BenchMARL, and no frame limit (the bar or the budget ends it; BenchMARL's own default is 3M frames).

    The task is VMAS's scenario as it is (VMAS issue #62): 100-step episodes where PettingZoo's MPE has 25,
    one goal drawn for all 10 training worlds at each reset, a reward of −2·distance shared by both agents
    (VMAS's scenario has no `collaborative` flag to set: its reward is the same for both), 9 moves of force 1.
    torchrl puts the speaker and the listener in separate groups (their observations differ), so MAPPO's
    centralised critic sees one agent, as IPPO's: the two differ here in little but name."""
    import dataclasses

    import torch
    from benchmarl.algorithms import IppoConfig, MappoConfig
    from benchmarl.environments import VmasTask
    from benchmarl.experiment import Callback, Experiment, ExperimentConfig
    from benchmarl.models.mlp import MlpConfig
    from benchmarl.utils import seed_everything
    from tensordict import TensorDict

    logging.getLogger("torchrl").setLevel(logging.WARNING)
    warnings.filterwarnings("ignore", message="No episode terminated")  # BenchMARL's logger, batches < an episode
    warnings.filterwarnings("ignore", message="SyncDataCollector has been deprecated")  # torchrl 0.11's note
    cfg = ExperimentConfig.get_from_yaml()  # benchmarl/conf/experiment/base_experiment.yaml
    cfg.sampling_device = cfg.train_device = cfg.buffer_device = "cpu"
    cfg.prefer_continuous_actions = False  # words are symbols: VMAS's discrete actions, as MPE's (default True)
    cfg.loggers, cfg.create_json, cfg.evaluation, cfg.render = [], False, False, False
    cfg.checkpoint_interval, cfg.checkpoint_at_end = 0, False
    if args.quick:
        cfg.on_policy_collected_frames_per_batch, cfg.on_policy_n_minibatch_iters, cfg.on_policy_minibatch_size = (
            1000, 1, 500)
    # the bar or the budget ends the run, not BenchMARL's 3M-frame default (a multiple of the batch: torchrl warns)
    cfg.max_n_frames = cfg.on_policy_collected_frames_per_batch * 10**8
    task = VmasTask.SIMPLE_SPEAKER_LISTENER.get_from_yaml()  # benchmarl/conf/task/vmas/simple_speaker_listener.yaml
    algo = (MappoConfig if algorithm == "mappo" else IppoConfig).get_from_yaml()
    world = VmasWorld(args.eval_worlds, task.config["max_steps"])
    actors: dict[str, Any] = {}

    def logits(group: str) -> Callable:
        def of(obs):  # BenchMARL's actor network: (n, 1 agent, obs) -> (n, 1, actions) logits
            td = TensorDict({group: TensorDict({"observation": obs.unsqueeze(1)}, batch_size=[len(obs), 1])},
                            batch_size=[len(obs)])
            return actors[group](td).get((group, "logits")).squeeze(1)
        return of

    race = Race(algorithm, lambda: judge(world, sampler(logits("speaker"), WORDS), sampler(logits("listener")),
                                         args.eval_seed), args.budget_cpu_s, args.check_cpu_s, args.check_growth)

    class Judge(Callback):
        def on_train_end(self, training_td, group):
            if group == list(self.experiment.group_map)[-1] and race.update(self.experiment.total_frames):
                raise Stop

    class Run(Experiment):
        def run(self):  # Experiment.run less its catch-all (which prints a failure), so Stop ends it quietly
            seed_everything(self.seed)
            try:
                self._collection_loop()
            except Stop:
                self.close()

    with tempfile.TemporaryDirectory() as folder:  # BenchMARL writes config.pkl to its experiment folder
        cfg.save_folder = folder
        race.start()
        exp = Run(task=task, algorithm_config=algo, model_config=MlpConfig.get_from_yaml(),
                  critic_model_config=MlpConfig.get_from_yaml(), seed=args.seed, config=cfg)
        judge_callback = Judge()  # added after setup, which pickles the callbacks (a local class would not)
        judge_callback.experiment = exp
        exp.callbacks.append(judge_callback)
        for group in exp.group_map:
            actors[group] = exp.algorithm.get_policy_for_loss(group).module[0]  # shares the trained weights
        exp.run()
    settings = {k: getattr(cfg, k) for k in (
        "on_policy_collected_frames_per_batch", "on_policy_n_envs_per_worker", "on_policy_n_minibatch_iters",
        "on_policy_minibatch_size", "lr", "adam_eps", "gamma", "clip_grad_norm", "clip_grad_val",
        "share_policy_params", "prefer_continuous_actions")}
    settings.update(task=dict(task.config), algorithm=dataclasses.asdict(algo), group_map=dict(exp.group_map),
                    model=MlpConfig.get_from_yaml().num_cells, torch_threads=torch.get_num_threads())
    return race.summary(trainer=f"benchmarl {algorithm}", world=f"VMAS's own scenario, {world.steps} steps",
                        episode_steps=world.steps, settings=settings)


def race_asp(args) -> dict[str, Any]:
    """asp-dist's base trainer (game.train_base's loop, unchanged, in chunks the judge can look between) at the
    vmas_speaker_listener defaults; denormals flushed as bases.train_accepted_base trains it."""
    import torch

    from asp_dist.domains.vmas import game
    from asp_dist.spec import CellSpec
    from asp_dist.training.float_mode import denormals_flushed

    spec = CellSpec(domain="vmas_speaker_listener", method="osp", trial=args.seed).resolved()
    seed, worlds, steps = spec.seed_for("base"), game.knob(spec, "base_worlds"), game.knob(spec, "episode_len")
    world = AspWorld(spec, args.eval_worlds)
    team_box: list = []
    race = Race("asp", lambda: judge(world, sampler(team_box[0].actors[0], None), sampler(team_box[0].actors[1]),
                                     args.eval_seed), args.budget_cpu_s, args.check_cpu_s, args.check_growth)
    episodes = 0
    with denormals_flushed():
        race.start()
        team = game.new_agents(spec, seed)  # as train_base: the team, its generator, Adam
        team_box.append(team)
        gen = torch.Generator().manual_seed(seed)
        opt = torch.optim.Adam(team.parameters(), lr=game.knob(spec, "base_lr"))
        while True:
            episode = game.play(spec, list(team.actors), worlds, game.draw_seed(gen), gen)
            opt.zero_grad(set_to_none=True)
            game.team_loss(spec, episode).backward()
            opt.step()
            episodes += 1
            if race.update(episodes * worlds * steps):
                break
    settings = {"base_worlds": worlds, "episode_len": steps, "base_lr": game.knob(spec, "base_lr"),
                "entropy": game.knob(spec, "entropy"), "hidden": game.knob(spec, "hidden"),
                "base_train_steps (train_base's own length)": spec.base_train_steps, "episodes": episodes,
                "base_seed": seed, "world_options": str(game.options(spec))}
    return race.summary(trainer="asp-dist train_base", world=f"asp-dist's (mpe2 on VMAS), {steps} steps",
                        episode_steps=steps, settings=settings)


def race_asp_pack(args) -> dict[str, Any]:
    """--pack-teams teams trained as one pack by asp-dist's packed trainer (asp_dist/domains/vmas/packed.py): OSP
    members without paired data, so pure self-play, at the base trainer's settings (episodes of base_worlds
    worlds, Adam base_lr, its entropy bonus), each from its own trial's seeds. The clock is the pack's, judged as
    the others' (its budget is --budget-cpu-s for the whole pack). A team counts once it has met the bar at a
    check (its first passage: a base is accepted at its first look that meets the bar); the pack stops when every
    team has, or at the budget. The figure beside one team's: the pack's CPU at its last first passage divided by
    the teams that passed (CPU-s per speaking team); a team that never passes is what a base's retry is for."""
    import torch

    from asp_dist.domains.vmas import game
    from asp_dist.domains.vmas.packed import PackedSpeakerListenerTrainer
    from asp_dist.spec import CellSpec
    from asp_dist.training.float_mode import denormals_flushed

    k = args.pack_teams
    base = CellSpec(domain="vmas_speaker_listener", method="osp").resolved()
    worlds, steps = game.knob(base, "base_worlds"), game.knob(base, "episode_len")
    specs = [CellSpec(domain=base.domain, method="osp", paired=0, trial=args.seed + i, batch_size=worlds,
                      lr=game.knob(base, "base_lr"), train_steps=10**7).resolved() for i in range(k)]
    world = AspWorld(specs[0], args.eval_worlds)
    box: list = []

    passed: dict[int, float] = {}  # team -> the pack's training CPU at its first passage

    def look() -> dict:  # every team judged alike; shown: the worst team still short of the bar
        figs = [judge(world, sampler(m.agents.actors[0], None), sampler(m.agents.actors[1]), args.eval_seed)
                for m in box[0].members]
        for i, f in enumerate(figs):
            if meets_bar(f) and i not in passed:
                passed[i] = race.now
        short = [f for i, f in enumerate(figs) if i not in passed] or figs
        return dict(min(short, key=lambda f: min(f["mi"] / BAR_MI, f["drop"] / BAR_DROP)), teams_passed=len(passed))

    race = Race("asp-pk", look, args.budget_cpu_s, args.check_cpu_s * k, args.check_growth,
                done=lambda fig: fig["teams_passed"] == k)
    updates = 0
    with denormals_flushed():
        race.start()
        box.append(PackedSpeakerListenerTrainer(specs, [{}] * k, [{}] * k,
                                                [game.new_agents(s, s.seed_for("init")) for s in specs]))
        while True:
            box[0].train_step()
            updates += 1
            if race.update(updates * worlds * steps * k):
                break
    out = race.summary(trainer=f"asp-dist pack of {k}", world=f"asp-dist's (mpe2 on VMAS), {steps} steps",
                       episode_steps=steps, teams=k, settings={"base_worlds": worlds, "episode_len": steps,
                                                               "lr": specs[0].lr, "updates": updates})
    per_team = max(passed.values()) / len(passed) if passed else None
    out.update(teams_passed=len(passed), first_passage_cpu_s=sorted(passed.values()),
               train_cpu_s_per_speaking_team=per_team)
    print(f"  asp-pk: {len(passed)} of {k} teams met the bar; " + (
        f"{per_team:.1f} CPU-s per speaking team" if passed else "none"), flush=True)
    return out


# ---- env steps ---------------------------------------------------------------------------------------------


@contextlib.contextmanager
def quiet_stdout():
    """Standard output closed at the descriptor (jaxmarl's import swaps sys.stdout back: redirect_stdout misses it)."""
    sys.stdout.flush()
    saved, null = os.dup(1), os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, 1)
    try:
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)
        os.close(null)


def jaxmarl_steps(b: int, repeats: int, min_s: float, roll: int = 25) -> dict[str, float]:
    """JaxMARL's MPE_simple_speaker_listener_v4 (25-step episodes, its step auto-resets), b worlds vmapped, random
    actions drawn inside the jitted function: `roll` steps per call (lax.scan) and one step per call."""
    import jax

    with quiet_stdout():  # its import prints that its optional submodules are absent
        import jaxmarl

    env = jaxmarl.make("MPE_simple_speaker_listener_v4")
    agents = list(env.agents)
    sizes = [env.action_space(a).n for a in agents]

    def one(key, state):
        keys = jax.random.split(key, len(agents) + 1)
        actions = {a: jax.random.randint(k, (), 0, n) for a, k, n in zip(agents, keys[1:], sizes)}
        _, state, reward, _, _ = env.step(keys[0], state, actions)
        return state, reward[agents[0]]

    def step(key, state):
        key, sub = jax.random.split(key)
        state, reward = jax.vmap(one)(jax.random.split(sub, b), state)
        return key, state, reward.sum()

    def rollout(key, state):
        def body(carry, _):
            key, state, reward = step(*carry)
            return (key, state), reward
        (key, state), rewards = jax.lax.scan(body, (key, state), None, length=roll)
        return key, state, rewards.sum()

    c0 = time.process_time()
    key = jax.random.PRNGKey(0)
    reset = jax.jit(jax.vmap(env.reset)).lower(jax.random.split(key, b)).compile()
    _, state = reset(jax.random.split(key, b))
    compiled = {"step": jax.jit(step).lower(key, state).compile(), "scan": jax.jit(rollout).lower(key, state).compile()}
    compile_cpu = time.process_time() - c0
    out = {"jaxmarl_compile_cpu_s": compile_cpu}
    for name, fn in compiled.items():
        carry = [key, state]

        def call():
            carry[0], carry[1], reward = fn(carry[0], carry[1])
            reward.block_until_ready()

        call()  # warm
        steps = b * (roll if name == "scan" else 1)
        out[f"jaxmarl_{name}_steps_per_cpu_s"] = steps / cpu_per_call(call, repeats, min_s)
    return out


def vmas_steps(b: int, repeats: int, min_s: float) -> dict[str, float]:
    """VMAS, b worlds as one batch, fixed random actions under no_grad: asp-dist's Worlds (its step, as
    bench/bench_vmas.py times it) and VMAS's own scenario through Environment.step (BenchMARL's world)."""
    import torch
    import vmas

    env = vmas.make_env("simple_speaker_listener", num_envs=b, device="cpu", continuous_actions=False, seed=0)
    actions = [torch.randint(27, (b, 1)), torch.randint(9, (b, 1))]
    t = [0]

    def own_step():
        with torch.no_grad():
            env.step(actions)
        t[0] += 1
        if t[0] >= 100:
            env.reset()
            t[0] = 0

    return {"vmas_asp_world_steps_per_cpu_s": vmas_random_steps_per_cpu_s(b, repeats, min_s),
            "vmas_own_scenario_steps_per_cpu_s": b / cpu_per_call(own_step, repeats, min_s)}


def mpe2_steps(b: int, repeats: int, min_s: float) -> dict[str, float]:
    """mpe2's copies through asp-dist's PettingZoo adapter (EnvBatch), as bench/bench_vmas.py's env_steps."""
    return {"mpe2_steps_per_cpu_s": mpe2_random_steps_per_cpu_s(b, repeats, min_s)}


def env_steps(args) -> dict[str, Any]:
    repeats, min_s = (1, 0.05) if args.quick else (3, 1.0)
    has_mpe2 = all(importlib.util.find_spec(m) is not None for m in ("mpe2", "pettingzoo"))
    rows = []
    for b in args.batches:
        row = {"batch": b, **jaxmarl_steps(b, repeats, min_s), **vmas_steps(b, repeats, min_s)}
        if has_mpe2:
            row.update(mpe2_steps(b, repeats, min_s))
        rows.append(row)
        print(f"  {b:5d} worlds: jaxmarl scan {row['jaxmarl_scan_steps_per_cpu_s']:12,.0f}  "
              f"step {row['jaxmarl_step_steps_per_cpu_s']:11,.0f}  (compile {row['jaxmarl_compile_cpu_s']:.1f} CPU-s)  "
              f"vmas asp-dist {row['vmas_asp_world_steps_per_cpu_s']:10,.0f}  "
              f"own {row['vmas_own_scenario_steps_per_cpu_s']:10,.0f}  "
              f"mpe2 {format(row['mpe2_steps_per_cpu_s'], '10,.0f') if has_mpe2 else 'not installed'}", flush=True)
    return {"rows": rows, "mpe2": "measured" if has_mpe2 else "skipped: mpe2/pettingzoo not installed in this venv "
            "(asp-dist's pettingzoo extra)", "repeats": repeats, "min_cpu_s_per_block": min_s}


# ---- main --------------------------------------------------------------------------------------------------
def versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for name in ("torch", "torchrl", "tensordict", "benchmarl", "vmas", "jax", "jaxlib", "jaxmarl", "asp-dist"):
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = "absent"
    return out


def table(race: dict[str, dict]) -> str:
    lines = [f"{'trainer':20s} {'world':36s} {'bar':4s} {'train CPU-s':>11s} {'wall s':>8s} {'world-steps':>13s} "
             f"{'MI':>6s} {'drop/25':>8s} {'best MI':>8s} {'best drop':>9s}"]
    for r in race.values():
        teams = r.get("teams", 1)  # a pack's CPU and wall per team, beside one team's
        lines.append(f"{r['trainer']:20s} {r['world']:36s} {'yes' if r['reached'] else 'no':4s} "
                     f"{r['train_cpu_s'] / teams:11.1f} {r['train_wall_s'] / teams:8.1f} {r['world_steps']:13,d} "
                     f"{r['mi']:6.3f} "
                     f"{r['drop']:8.2f} {r['best_mi']:8.3f} {r['best_drop']:9.2f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    one_core(args.core)
    import torch

    torch.set_num_threads(1)
    result: dict[str, Any] = {
        "machine": machine_info(), "versions": versions(), "core": args.core, "load_before": os.getloadavg()[0],
        "flags": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "bar": {"mi_nats": BAR_MI, "drop_dist2_per_25_steps": BAR_DROP}, "race": {}}
    print(f"load average {result['load_before']:.2f}; pinned to core {args.core}; budget {args.budget_cpu_s:g} "
          f"training CPU-s per trainer, judged after {args.check_cpu_s:g} CPU-s and every {args.check_growth:.0%} "
          f"more, on {args.eval_worlds} worlds; "
          f"bar MI >= {BAR_MI} and drop >= {BAR_DROP} per {DROP_STEPS} steps", flush=True)
    cpu0, wall0 = time.process_time(), time.perf_counter()
    trainers = {"mappo": lambda: race_benchmarl("mappo", args), "ippo": lambda: race_benchmarl("ippo", args),
                "asp": lambda: race_asp(args), "asp-pack": lambda: race_asp_pack(args)}
    for peer, race in trainers.items():
        if peer in args.peers:
            result["race"][peer] = race()
            if args.json:  # after every trainer: a stopped run keeps what it measured
                args.json.write_text(json.dumps(result, indent=1, default=str))
    if "steps" in args.peers:
        print("world-steps per CPU-second, random actions (compile CPU apart):", flush=True)
        result["env_steps"] = env_steps(args)
    result.update(total_cpu_s=time.process_time() - cpu0, total_wall_s=time.perf_counter() - wall0,
                  load_after=os.getloadavg()[0])
    if result["race"]:
        print(table(result["race"]))
    print(f"total {result['total_cpu_s']:.1f} CPU-s, {result['total_wall_s']:.1f} s wall; load average "
          f"{result['load_after']:.2f}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
