"""The fixed cells whose rows must not change when code is moved or knobs are added.

Every domain and method at short budgets, plus a particle cell on the autograd path and one
with the non-saturating loss. `(cd tests && python -m golden.record)` writes their rows (without the
volatile columns) to tests/golden/rows.parquet; tests/test_golden_rows.py reruns them and
compares. Record only on purpose: a changed row means changed behaviour.
"""

from __future__ import annotations

# A frozen copy of tests/budgets.py as it was when the rows were recorded: the shared budgets may
# change for other tests, these cells must not.
TINY = {
    "signaling": dict(train_steps=60, batch_size=16, unpaired_size=128),
    "particles": dict(train_steps=40, base_train_steps=30, particles_base_envs=32, eval_episodes=64,
                      unpaired_size=256, particles_hidden=16, particles_message_dim=16,
                      particles_accept_return=0.0),
    "vae": dict(vae_train_images=300, vae_hidden=64, vae_latent_dim=4, base_train_steps=40, vae_base_batch=32,
                train_steps=20, batch_size=32, unpaired_size=64, eval_episodes=200, disc_hidden=16),
    "levers": dict(levers_hidden=8, base_train_steps=30, train_steps=20, batch_size=16, levers_replay_size=64,
                   unpaired_size=60, disc_hidden=8, eval_episodes=120, levers_accept_reward=0.0),
}


# The defaults in force when the rows were recorded, where a domain's default changed since on
# purpose (the reproduction study, 2026-11-25: docs/decisions/0021-domain-defaults-from-reproduction-study.md).
# Pinned so the rows keep checking that the code did not change behaviour; the new defaults are tested in
# test_knobs.py.
OLD_DEFAULTS = {
    "particles": dict(lambda_unpaired_schedule="constant", base_steps_growth=1.0, base_max_attempts=5),
    "vae": dict(lambda_unpaired=1.0),
}


def golden_specs() -> list[dict]:
    """Plain dicts (not CellSpec) so that the list itself survives module moves."""
    out = []
    for domain, knobs in TINY.items():
        knobs = {**knobs, **OLD_DEFAULTS.get(domain, {})}
        for method in ("pc", "osp", "asp"):
            out.append(dict(domain=domain, method=method, paired=2, trial=3, **knobs))
    out.append(dict(domain="particles", method="asp", paired=1, trial=4, adversary_loss="non_saturating",
                    **TINY["particles"], **OLD_DEFAULTS["particles"]))
    return out
