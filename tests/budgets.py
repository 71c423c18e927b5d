"""Every budget shrunk so that a cell of any domain runs in about a second: the one place tests
get small specs from (the `tiny` fixture in conftest.py, and tests/golden/cells.py).

TINY pins the four built-ins' values (the golden rows were recorded with them; each equals its domain's
Domain.smoke); any other registered domain, a plugin's, runs with its own Domain.smoke."""

from __future__ import annotations

TINY: dict[str, dict] = {
    "signaling": dict(train_steps=60, batch_size=16, unpaired_size=128),
    "particles": dict(train_steps=40, base_train_steps=30, particles_base_envs=32, eval_episodes=64,
                      unpaired_size=256, particles_hidden=16, particles_message_dim=16,
                      particles_accept_return=0.0),
    "vae": dict(vae_train_images=300, vae_hidden=64, vae_latent_dim=4, base_train_steps=40, vae_base_batch=32,
                train_steps=20, batch_size=32, unpaired_size=64, eval_episodes=200, disc_hidden=16),
    "levers": dict(levers_hidden=8, base_train_steps=30, train_steps=20, batch_size=16, levers_replay_size=64,
                   unpaired_size=60, disc_hidden=8, eval_episodes=120, levers_accept_reward=0.0),
}


def tiny_spec(domain: str, **changes):
    from asp_dist.core.registry import get_domain
    from asp_dist.spec import CellSpec

    small = TINY[domain] if domain in TINY else get_domain(domain).smoke
    return CellSpec(domain=domain, **{**small, **changes})
