"""Every domain, by name. Add a domain here and every registry-wide test runs on it."""

from __future__ import annotations

from asp_dist.domains.contract import Domain
from asp_dist.domains.levers import LeversDomain
from asp_dist.domains.particles import ParticlesDomain
from asp_dist.domains.signaling import SignalingDomain
from asp_dist.domains.vae import VAEDomain
from asp_dist.errors import SpecError

DOMAINS: dict[str, Domain] = {d.name: d for d in (SignalingDomain(), ParticlesDomain(), VAEDomain(), LeversDomain())}


def get_domain(name: str) -> Domain:
    try:
        return DOMAINS[name]
    except KeyError:
        raise SpecError(f"unknown domain {name!r}; choose one of {', '.join(sorted(DOMAINS))}") from None
