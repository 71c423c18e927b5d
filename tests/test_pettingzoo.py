"""The PettingZoo adapter (asp_dist/domains/pettingzoo/): its two declarations (MPE's speaker–listener and
simple_reference) keep the contract, bad environments, agents, channels and spaces are one-line errors at
resolution, the domains are set aside with one line when the extra is missing, and `--help` stays light.

Needs the `pettingzoo` extra (in the `test` extra): pettingzoo 1.27.0 and mpe2 1.1.1.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pettingzoo")
pytest.importorskip("mpe2")

import torch  # noqa: E402
from gymnasium import spaces  # noqa: E402
from harness import cli  # noqa: E402
from pettingzoo import ParallelEnv  # noqa: E402

from asp_dist.core.registry import DOMAINS, get_domain  # noqa: E402
from asp_dist.domains.pettingzoo import INSTALL, MPEReference, MPESpeakerListener, PettingZooDomain, PettingZooGame  # noqa: E402
from asp_dist.errors import SpecError  # noqa: E402
from asp_dist.spec import CellSpec  # noqa: E402
from asp_dist.training.cell import run_cell  # noqa: E402

SL, REF = "mpe_speaker_listener", "mpe_reference"
NAMES = (SL, REF)
TESTS = str(Path(__file__).parent)


def smoke(name: str, **changes) -> CellSpec:
    return CellSpec(domain=name, **{**get_domain(name).smoke, **changes})


# ---- environments the adapter must refuse (named in knobs as test_pettingzoo:<factory>) -------------------
class TinyEnv(ParallelEnv):
    """Two agents, one step per episode; the spaces are the test's."""

    metadata = {"name": "tiny"}

    def __init__(self, action_space, agents=("speaker_0", "listener_0"), obs_space=None):
        self.possible_agents = list(agents)
        self._action = action_space
        self._obs = obs_space or spaces.Box(-1.0, 1.0, (2,), np.float32)

    def observation_space(self, agent):
        return self._obs

    def action_space(self, agent):
        return self._action

    def reset(self, seed=None, options=None):
        self.agents = list(self.possible_agents)
        return {a: self._obs.sample() for a in self.agents}, {a: {} for a in self.agents}

    def step(self, actions):
        self.agents = []
        obs = {a: self._obs.sample() for a in self.possible_agents}
        flags = {a: True for a in self.possible_agents}
        return obs, {a: 0.0 for a in self.possible_agents}, flags, flags, {a: {} for a in self.possible_agents}


def dict_actions(**_):
    return TinyEnv(spaces.Dict({"a": spaces.Discrete(2)}))


def unbounded_box(**_):
    return TinyEnv(spaces.Box(-np.inf, np.inf, (3,), np.float32))


def text_observations(**_):
    return TinyEnv(spaces.Discrete(5), obs_space=spaces.Text(5))


def seven_actions(**_):
    return TinyEnv(spaces.Discrete(7), agents=("agent_0", "agent_1"))


# ---- declarations -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("name, cls", [(SL, MPESpeakerListener), (REF, MPEReference)])
def test_declarations_make_registered_domains(name, cls):
    domain = DOMAINS[name]
    assert isinstance(domain, cls) and domain.name == name and not domain.legacy_identity
    assert all(k.name.startswith(f"{name}_") for k in domain.knobs)
    assert domain.accept_field == f"{name}_accept_gain" and domain.channels == ("channel",)
    assert {"mixed", "self_play_new", "self_play_base"} <= set(domain.metrics)
    spec = CellSpec(domain=name).resolved()  # the defaults resolve: the env is found, its spaces usable
    assert getattr(spec, f"{name}_env") == cls.declaration.env
    facts = domain.facts(spec)
    assert facts.names == tuple(cls.declaration.parts)
    assert getattr(spec, f"{name}_new_agent") in facts.names


def test_the_adapter_reads_each_declarations_action_parts():
    sl = get_domain(SL).facts(CellSpec(domain=SL).resolved())
    assert [(a.name, a.kind, a.parts) for a in sl.agents] == [("speaker_0", "discrete", (("say", 3),)),
                                                              ("listener_0", "discrete", (("move", 5),))]
    assert [a.obs_dim for a in sl.agents] == [3, 11]
    ref = get_domain(REF)
    spec = CellSpec(domain=REF).resolved()
    agent, index, size = ref.role(spec)  # Discrete(50) = move + 5 × say
    assert (agent.name, agent.kind, index, size) == ("agent_1", "discrete", 1, 10)
    assert ref.channel_dims(spec) == {"channel": 10}
    cont = ref.facts(spec.replace(mpe_reference_continuous=True))  # Box(15) = 5 move dims, then 10 say dims
    assert (cont.agents[1].kind, cont.agents[1].width, cont.agents[1].part_offset(1)) == ("box", 15, 5)


def test_a_bad_declaration_is_refused_when_its_class_is_made():
    with pytest.raises(TypeError, match="team_reward must be one of sum, mean, shared"):
        type("Bad", (PettingZooDomain,), {"name": "bad", "declaration": PettingZooGame(
            env="mpe2.simple_v3", new_agent="agent_0", channel="action", team_reward="max")})
    assert PettingZooGame(env="x", new_agent="a", channel="c", parts={"a": (("c", 0),)}).problems()


def test_a_second_environment_is_a_declaration_away():
    """The researcher's side: a class with a declaration, knobs named after it (not registered here)."""

    class Spread(PettingZooDomain):
        name = "mpe_spread"
        declaration = PettingZooGame(env="mpe2.simple_spread_v3", env_kwargs={"N": 2}, new_agent="agent_1",
                                     channel="action", team_reward="mean", accept_gain=5.0)

    domain = Spread()
    assert [k.name for k in domain.knobs][:3] == ["mpe_spread_env", "mpe_spread_new_agent", "mpe_spread_channel"]
    assert domain.smoke["mpe_spread_accept_gain"] == 0.0 and domain.game.__name__.endswith("pettingzoo.game")


# ---- bad input: one line at resolution ---------------------------------------------------------------------
BAD = [
    (SL, {"env": "mpe2.no_such_env_v1"}, "mpe_speaker_listener_env: no environment 'mpe2.no_such_env_v1'"),
    (SL, {"env": "mpe2.simple_speaker_listener_v4:no_factory"}, "has no environment factory 'no_factory'"),
    (SL, {"env": "mpe2.simple_speaker_listener_v4:env"}, "made an AEC env .*not a PettingZoo parallel environment"),
    (SL, {"env": "not a module"}, "must be 'package.module' or 'package.module:factory'"),
    (SL, {"new_agent": "ghost"}, "mpe_speaker_listener_new_agent 'ghost' is not an agent of .*its agents: "
                                 "speaker_0, listener_0"),
    (SL, {"channel": "say"}, "mpe_speaker_listener_channel 'say' is not a part of listener_0's action .*"
                             r"its parts: move \(5\)"),
    (SL, {"env": "mpe2.simple_reference_v3"}, "has no agent 'listener_0' or 'speaker_0'"),
    (REF, {"team_reward": "shared"}, "team reward 'shared' but its agents' rewards differ"),
    (SL, {"env": "test_pettingzoo:dict_actions"}, "action space Dict.*which the adapter cannot use"),
    (SL, {"env": "test_pettingzoo:unbounded_box"}, "unbounded; the adapter takes Box actions with finite bounds"),
    (SL, {"env": "test_pettingzoo:text_observations"}, "observation space Text.*which the adapter cannot use"),
    (REF, {"env": "test_pettingzoo:seven_actions"}, r"action parts \(move: 5, say: 10\) multiply to 50, but its "
                                                   r"action space is Discrete\(7\)"),
    (SL, {"hidden": 0}, "mpe_speaker_listener_hidden must be >= 1"),
    (SL, {"gamma": 1.5}, r"mpe_speaker_listener_gamma must be in \[0, 1\]"),
]


@pytest.mark.parametrize("name, knobs, message", BAD, ids=[f"{n}-{next(iter(k.values()))}" for n, k, _ in BAD])
def test_bad_input_is_one_line_at_resolution(name, knobs, message):
    with pytest.raises(SpecError, match=message) as err:
        CellSpec(domain=name, method="asp", paired=2, **{f"{name}_{k}": v for k, v in knobs.items()}).resolved()
    assert "\n" not in str(err.value)


def test_bad_input_through_the_cli_writes_nothing(tmp_path):
    out = tmp_path / "row.parquet"
    for knob in (f"{SL}_env=mpe2.no_such_env_v1", f"{SL}_channel=say", f"{SL}_env=test_pettingzoo:dict_actions"):
        done = cli("cell", "--domain", SL, "--method", "pc", "--paired", "2", "--set", knob, "--out", str(out),
                   timeout=120, PYTHONPATH=TESTS)
        assert done.returncode == 2, done.stderr
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("asp-dist: error: "), done.stderr
    assert not out.exists()


# ---- the extra missing; --help light ---------------------------------------------------------------------
MISSING = """
import sys
sys.modules["mpe2"] = None  # as if the extra were not installed: importlib.util.find_spec("mpe2") is None
from asp_dist.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_without_the_extra_each_domain_is_set_aside_with_one_line():
    fields = subprocess.run([sys.executable, "-c", MISSING, "fields"], capture_output=True, text=True, timeout=120)
    assert fields.returncode == 0, fields.stderr
    for name in NAMES:
        lines = [line for line in fields.stderr.splitlines() if f"'{name}'" in line]
        assert len(lines) == 1 and INSTALL in lines[0] and "mpe2 is not installed" in lines[0], fields.stderr
    check = subprocess.run([sys.executable, "-c", MISSING, "check-domain", SL], capture_output=True, text=True,
                           timeout=120)
    assert check.returncode == 2
    assert check.stderr.count("\n") == 1 and check.stderr.startswith("asp-dist: error: ") and INSTALL in check.stderr


LIGHT = """
import json, sys
from asp_dist.cli import main
try:
    main(sys.argv[1:])
except SystemExit:
    pass
print("MODULES:" + json.dumps(sorted({m.split(".")[0] for m in sys.modules} & {"torch", "ray", "pettingzoo", "mpe2",
                                                                                  "gymnasium", "pygame"})))
"""


@pytest.mark.parametrize("argv", [["--help"], ["fields", "--domain", SL]], ids=["help", "fields"])
def test_describing_commands_import_no_pettingzoo(argv):
    done = subprocess.run([sys.executable, "-c", LIGHT, *argv], capture_output=True, text=True, timeout=120)
    line = next(x for x in done.stdout.splitlines() if x.startswith("MODULES:"))
    assert json.loads(line.removeprefix("MODULES:")) == [], done.stdout[-500:]


# ---- the contract, the methods, resuming self-play -------------------------------------------------------
@pytest.mark.parametrize("name", NAMES)
def test_check_domain_passes(name):
    done = cli("check-domain", name, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    assert f"domain {name}: passes the contract" in done.stdout


@pytest.mark.parametrize("method", ["pc", "osp", "asp"])
def test_each_method_runs_with_continuous_actions(method):
    """The Box path (a Gaussian policy; the channel its slice of the action) on MPE's continuous speaker–listener."""
    row = run_cell(smoke(SL, method=method, paired=2, mpe_speaker_listener_continuous=True,
                         mpe_speaker_listener_new_agent="speaker_0", mpe_speaker_listener_channel="say"))
    assert row["method"] == method and row["mpe_speaker_listener_continuous"] is True
    assert all(np.isfinite(row[f"eval_{m}"]) for m in get_domain(SL).metrics)
    assert (row["loss_unpaired"] is not None) == (method == "asp")


@pytest.mark.parametrize("name, continuous", [(SL, False), (REF, False), (REF, True)])
def test_self_play_resumes_from_its_state_alone(name, continuous):
    """A copy of the state (as a checkpoint restores it) rebuilds the env copies by replaying their episodes and
    continues exactly as the live state does."""
    domain = get_domain(name)
    spec = smoke(name, method="osp", **{f"{name}_continuous": continuous}).resolved()
    agents = domain.new_agents(spec, 1)
    gen = torch.Generator().manual_seed(0)
    state = domain.init_self_play(spec, agents, gen)
    for _ in range(7):
        domain.self_play_step(spec, agents, state, gen)
    copy = {k: v.clone() for k, v in state.items()}
    gen_copy = torch.Generator()
    gen_copy.set_state(gen.get_state())
    live = [domain.self_play_step(spec, agents, state, gen) for _ in range(5)]
    restored = [domain.self_play_step(spec, agents, copy, gen_copy) for _ in range(5)]
    for a, b in zip(live, restored):
        assert torch.equal(a.loss, b.loss) and torch.equal(a.outputs["channel"], b.outputs["channel"])
    assert all(torch.equal(state[k], copy[k]) for k in state)


def test_mixed_is_the_new_agent_beside_the_base():
    """Eq. 1 with one new agent: a new team whose new agent is the base's own plays exactly the base's episodes."""
    domain = get_domain(SL)
    spec = smoke(SL, method="osp", eval_episodes=16).resolved()
    base, _ = domain.train_base(spec, seed=3)
    agents = domain.new_agents(spec, 5)
    agents.actors[1].load_state_dict(base.actors[1].state_dict())  # listener_0, the new agent
    m = domain.evaluate(spec, base, agents, torch.Generator().manual_seed(0))
    assert m["mixed"] == m["self_play_base"] and m["channel_match"] == 1.0
    assert m["mixed_swapped"] == m["self_play_new"]  # base listener + the new (untrained) speaker


def test_unpaired_outputs_are_one_hot_base_actions():
    domain = get_domain(REF)
    spec = smoke(REF, method="asp").resolved()
    base, _ = domain.train_base(spec, seed=1)
    u = domain.unpaired(spec, base, 40, torch.Generator().manual_seed(0))["channel"]
    assert u.shape == (40, 10) and torch.equal(u.sum(1), torch.ones(40)) and set(u.unique().tolist()) == {0.0, 1.0}
    p = domain.paired(spec, base, 5, torch.Generator().manual_seed(0))
    assert p["obs"].shape == (5, 21) and p["action"].shape == (5, 2)  # (move, say) of agent_1
