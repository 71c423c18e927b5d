"""The CommNet lever domain: the reward, the mixed-team forward pass, the contract, determinism,
one smoke cell per method, checkpoint/restore, and a mixed team of a network with itself.

Budgets are shrunk (hidden 8, tens of updates, acceptance bar off) so the file runs in seconds;
the default-size base (reward >= 0.95) is checked in the one slow test and in bench/bench_levers.py."""

import copy
import json

import pytest
import torch
from budgets import tiny_spec
from checkpoints import checkpoint_sink

from asp_dist.core.registry import get_domain
from asp_dist.domains.levers import (
    AGENTS,
    CommNet,
    all_games,
    communicate,
    draw_games,
    eval_games,
    seat_arrangements,
    team_forward,
    team_reward,
)
from asp_dist.spec import CellSpec, SpecError
from asp_dist.training import artefacts
from asp_dist.training.bases import train_accepted_base
from asp_dist.training.cell import run_cell
from asp_dist.training.row import comparable


def tiny(**changes) -> CellSpec:
    return tiny_spec("levers", **changes)


@pytest.fixture(scope="module")
def domain():
    return get_domain("levers")


@pytest.fixture(scope="module")
def base():
    return train_accepted_base(tiny(paired=4))


# ---- the game -------------------------------------------------------------------------------------
def reference_reward(ids, levers):
    """Literal reading of the rule: lever i counts if the agent with the i-th smallest ID pulled it."""
    order = sorted(range(AGENTS), key=lambda s: ids[s])
    return sum(levers[order[i]] == i for i in range(AGENTS)) / AGENTS


@pytest.mark.parametrize("ids, levers, expected", [
    ((8, 3, 5), (0, 1, 1), 1 / 3),   # the paper's example
    ((8, 3, 5), (2, 0, 1), 1.0),     # sorted: 3 -> lever 0, 5 -> 1, 8 -> 2
    ((0, 1, 2), (0, 0, 0), 1 / 3),   # everyone on lever 0: only the smallest ID is right
    ((9, 0, 4), (0, 2, 1), 1 / 3),   # only the middle ID right
    ((2, 7, 5), (1, 0, 2), 0.0),
])
def test_reward_on_hand_made_cases(ids, levers, expected):
    got = team_reward(torch.tensor([ids]), torch.tensor([levers]))
    assert got.shape == (1,)
    assert float(got[0]) == pytest.approx(expected)


def test_reward_is_vectorised_and_matches_the_rule_on_every_game():
    games = all_games(6)
    levers = torch.randint(AGENTS, games.shape, generator=torch.Generator().manual_seed(0))
    got = team_reward(games, levers)
    want = torch.tensor([reference_reward(g.tolist(), a.tolist()) for g, a in zip(games, levers)])
    assert torch.allclose(got, want)


def test_games_have_distinct_ids_and_the_exhaustive_set_is_complete():
    games = draw_games(10, 500, torch.Generator().manual_seed(1))
    assert games.shape == (500, 3) and int(games.min()) >= 0 and int(games.max()) <= 9
    assert all(len(set(g)) == 3 for g in games.tolist())
    every = all_games(10)
    assert len(every) == 720 == len({tuple(g) for g in every.tolist()})


# ---- the network and mixed teams ------------------------------------------------------------------
def test_communication_is_the_mean_of_the_other_agents():
    h = torch.tensor([[[1.0], [2.0], [6.0]]])
    assert communicate(h).flatten().tolist() == [4.0, 3.5, 1.5]


def test_mixed_team_runs_each_seat_on_its_own_network_and_mixes_the_messages():
    torch.manual_seed(0)
    a, b = CommNet(10, 8), CommNet(10, 8)
    ids = torch.tensor([[8, 3, 5], [0, 9, 1]])
    seats = torch.tensor([[1, 0, 0], [0, 1, 1]])  # 1 = network b
    h1, h2, q = team_forward([a, b], seats, ids)
    with torch.no_grad():
        nets = [[a, b][int(s)] for s in seats.flatten()]
        flat_ids = ids.flatten()
        want_h1 = torch.stack([n.block1(i) for n, i in zip(nets, flat_ids)]).view(2, 3, -1)
        c1 = communicate(want_h1)
        want_h2 = torch.stack([n.block2(x, c) for n, x, c in zip(nets, want_h1.view(6, -1), c1.view(6, -1))])
        want_q = torch.stack([n.q(x) for n, x in zip(nets, want_h2)])
    assert torch.allclose(h1, want_h1) and torch.allclose(h2, want_h2.view(2, 3, -1))
    assert torch.allclose(q, want_q.view(2, 3, -1))


def test_seat_arrangements_cover_every_seating():
    assert sorted(map(tuple, seat_arrangements(1).tolist())) == [(0, 0, 1), (0, 1, 0), (1, 0, 0)]
    assert sorted(map(tuple, seat_arrangements(2).tolist())) == [(0, 1, 1), (1, 0, 1), (1, 1, 0)]


def test_mixed_team_of_a_network_with_itself_scores_exactly_its_self_play(domain, base):
    spec = tiny().resolved()
    twin = copy.deepcopy(base.agents)
    m = domain.evaluate(spec, base.agents, twin, torch.Generator().manual_seed(0))
    assert m["reward_1new_2base"] == m["reward_2new_1base"] == 1.0 - m["self_play_base"]
    assert m["mixed"] == m["self_play_new"] == m["self_play_base"]
    assert m["lever_match"] == 1.0
    same = domain.evaluate(spec, base.agents, base.agents, torch.Generator().manual_seed(0))
    assert same == m


def test_evaluation_is_exhaustive_at_the_default_size(domain, base):
    spec = tiny(eval_episodes=720).resolved()
    assert torch.equal(eval_games(spec, torch.Generator().manual_seed(5)), all_games(10))


# ---- contract, data, training ---------------------------------------------------------------------
def test_paired_set_holds_base_outputs_for_its_ids(domain, base):
    spec = tiny().resolved()
    p = domain.paired(spec, base.agents, 5, torch.Generator().manual_seed(0))
    assert p["ids"].shape == (5, 3) and p["f1"].shape == (5, 3, 8) and p["f2"].shape == (5, 3, 8)
    h1, h2, q = base.agents(p["ids"])
    assert torch.equal(h1, p["f1"]) and torch.equal(h2, p["f2"]) and torch.equal(q.argmax(-1), p["levers"])
    fresh = domain.new_agents(spec, 99)
    # The base fits its own paired set better than a fresh network (its MSE terms are exactly 0).
    assert domain.paired_loss(spec, base.agents, p) < domain.paired_loss(spec, fresh, p)


def test_replay_buffer_fills_wraps_and_lives_in_the_state(domain):
    spec = tiny(batch_size=16, levers_replay_size=40).resolved()
    net = domain.new_agents(spec, 0)
    state = domain.init_self_play(spec, net, torch.Generator().manual_seed(0))
    gen = torch.Generator().manual_seed(0)
    for _ in range(3):
        out = domain.self_play_step(spec, net, state, gen)
    assert int(state["filled"]) == 40 and int(state["pos"]) == 48 % 40 and int(state["step"]) == 3
    assert out.outputs["f1"].shape == (2 * 16 * 3, 8) and out.outputs["f1"].requires_grad
    ok = team_reward(state["ids"], state["levers"])
    assert torch.equal(ok, state["reward"])  # stored rewards belong to the stored games


def test_bad_knobs_are_spec_errors():
    with pytest.raises(SpecError, match="levers_num_ids"):
        tiny(levers_num_ids=2).resolved()
    with pytest.raises(SpecError, match="levers_replay_size"):
        tiny(levers_replay_size=8).resolved()
    with pytest.raises(SpecError, match="levers_eps_end"):
        tiny(levers_eps_end=1.5).resolved()


@pytest.mark.parametrize("method", ["pc", "osp", "asp"])
def test_smoke_cell_per_method(base, method):
    row = run_cell(tiny(method=method, paired=4), base=base)
    assert row["domain"] == "levers" and row["method"] == method
    assert 0.0 <= row["eval_mixed"] <= 1.0
    assert row["eval_mixed"] == pytest.approx(1 - (row["eval_reward_1new_2base"] + row["eval_reward_2new_1base"]) / 2)
    assert row["eval_mixed_higher_is_better"] is False
    assert json.loads(row["metric_directions"])["self_play_new"] == "lower"
    assert (row["loss_unpaired"] is not None) == (method == "asp")
    assert (row["loss_self_play"] is not None) == (method != "pc")


def test_whole_cell_is_deterministic(base):
    spec = tiny(method="asp", paired=2)
    assert comparable(run_cell(spec, base=base)) == comparable(run_cell(spec, base=base))


def test_restored_cell_equals_the_uninterrupted_one(base):
    spec = tiny(method="asp", paired=2)
    saved, keep = checkpoint_sink()

    full = run_cell(spec, base=base, checkpoint=keep, checkpoint_every_steps=7)
    resumed = run_cell(spec, base=base, restore=artefacts.from_bytes(saved[0], "checkpoint"))
    assert resumed["resumed_from_step"] == 7
    assert {k: v for k, v in comparable(resumed).items() if k != "resumed_from_step"} == \
        {k: v for k, v in comparable(full).items() if k != "resumed_from_step"}


def test_figure_data_holds_last_block_vectors_coloured_by_id(base):
    row = run_cell(tiny(method="osp", paired=2, record_figure_data=True), base=base)
    fig = json.loads(row["figure_data"])
    assert fig["kind"] == "comm"
    assert len(fig["base"]) == len(fig["new"]) == len(fig["ids"]) == 150
    assert len(fig["base"][0]) == 8 and set(fig["ids"]) <= set(range(10))


@pytest.mark.slow
def test_default_base_reaches_the_papers_bar():
    base = train_accepted_base(CellSpec(domain="levers", trial=0))
    assert base.score >= 0.95
