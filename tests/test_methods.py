"""Loss composition: methods are weights on one loss, L = w_sp·L_sp + λ0·L_p + λ1·L_u."""

import torch

from asp_dist.core.registry import get_domain
from asp_dist.spec import CellSpec
from asp_dist.training.methods import compose_loss, method_weights
from asp_dist.training.trainer import Trainer


def terms():
    return torch.tensor(1.25), torch.tensor(0.5), torch.tensor(-0.75)


def test_zero_lambdas_give_exactly_the_self_play_loss():
    sp, p, u = terms()
    for method in ("osp", "asp"):
        w = method_weights(CellSpec(domain="signaling", method=method, paired=3, lambda_paired=0.0, lambda_unpaired=0.0))
        assert torch.equal(compose_loss(w, sp, p, u), sp)
        assert torch.equal(compose_loss(w, sp, None, None), sp)


def test_weighted_sum():
    sp, p, u = terms()
    w = method_weights(CellSpec(domain="signaling", method="asp", paired=3, lambda_paired=0.5, lambda_unpaired=2.0))
    assert torch.isclose(compose_loss(w, sp, p, u), sp + 0.5 * p + 2.0 * u)


def test_method_weights():
    base = dict(domain="signaling", paired=2, lambda_paired=0.7, lambda_unpaired=0.3)
    pc, osp, asp = (method_weights(CellSpec(method=m, **base)) for m in ("pc", "osp", "asp"))
    assert (pc.self_play, pc.paired, pc.unpaired) == (0.0, 0.7, 0.0)
    assert (osp.self_play, osp.paired, osp.unpaired) == (1.0, 0.7, 0.0)
    assert (asp.self_play, asp.paired, asp.unpaired) == (1.0, 0.7, 0.3)
    assert method_weights(CellSpec(method="asp", **{**base, "paired": 0})).paired == 0.0


class Spy:
    """Wraps a domain, counting the loss terms the trainer asks for."""

    def __init__(self, domain):
        self.domain, self.calls = domain, {"self_play": 0, "paired": 0, "convention": 0}

    def __getattr__(self, name):
        return getattr(self.domain, name)

    def self_play_step(self, *a, **k):
        self.calls["self_play"] += 1
        return self.domain.self_play_step(*a, **k)

    def paired_loss(self, *a, **k):
        self.calls["paired"] += 1
        return self.domain.paired_loss(*a, **k)

    def convention_outputs(self, *a, **k):
        self.calls["convention"] += 1
        return self.domain.convention_outputs(*a, **k)


def make_trainer(method, **changes):
    spec = CellSpec(domain="signaling", method=method, paired=3, trial=0, train_steps=5, **changes).resolved()
    spy = Spy(get_domain("signaling"))
    from asp_dist.training.bases import train_accepted_base

    base = train_accepted_base(spec)
    gen = torch.Generator().manual_seed(0)
    paired = spy.domain.paired(spec, base.agents, spec.paired, gen)
    unpaired = spy.domain.unpaired(spec, base.agents, 64, gen)
    agents = spy.domain.new_agents(spec, 1)
    return Trainer(spec, spy, agents, paired, unpaired, method_weights(spec)), spy


def test_pc_never_runs_self_play_or_adversaries():
    trainer, spy = make_trainer("pc")
    for _ in range(5):
        trainer.train_step()
    assert spy.calls == {"self_play": 0, "paired": 5, "convention": 0}
    assert trainer.adversaries is None


def test_osp_interleaves_self_play_and_paired_every_update():
    trainer, spy = make_trainer("osp")
    for _ in range(5):
        trainer.train_step()
    assert spy.calls["self_play"] == 5 and spy.calls["paired"] == 5 and trainer.adversaries is None


def test_asp_with_zero_lambdas_trains_exactly_like_pure_self_play():
    """λ0 = λ1 = 0: the trainer follows a hand-written pure self-play loop, bit for bit."""
    trainer, spy = make_trainer("asp", lambda_paired=0.0, lambda_unpaired=0.0)
    domain, spec = spy.domain, trainer.spec
    agents = domain.new_agents(spec, 1)
    opt = torch.optim.Adam(agents.parameters(), lr=spec.lr)
    gen = torch.Generator().set_state(trainer.gen.get_state())
    state = {k: v.clone() for k, v in trainer.sp_state.items()}
    for _ in range(5):
        trainer.train_step()
        loss = domain.self_play_step(spec, agents, state, gen).loss
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert spy.calls["paired"] == 0 and trainer.adversaries is None
    for (name, pa), pb in zip(trainer.agents.state_dict().items(), agents.state_dict().values()):
        assert torch.equal(pa, pb), name


def test_asp_trains_one_discriminator_per_channel():
    trainer, spy = make_trainer("asp", lambda_unpaired=1.0)
    before = {k: v.clone() for k, v in trainer.adversaries.state_dict().items()}
    trainer.train_step()
    assert set(trainer.adversaries.discs) == set(get_domain("signaling").channels)
    after = trainer.adversaries.state_dict()
    assert any(not torch.equal(before[k], after[k]) for k in before)
