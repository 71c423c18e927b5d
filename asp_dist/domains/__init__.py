"""Domain registry. Domains import lazily so that a test of one does not pay for the others."""

from __future__ import annotations

import importlib
import importlib.util

from asp_dist.spec import SpecError

# name -> "module:Class"; a domain appears here once its module exists.
DOMAINS: dict[str, str] = {
    "signaling": "asp_dist.domains.signaling:SignalingDomain",
    "particles": "asp_dist.domains.particles:ParticlesDomain",
    "vae": "asp_dist.domains.vae:VAEDomain",
    "levers": "asp_dist.domains.levers:LeversDomain",
}

_instances: dict = {}


def available_domains() -> list[str]:
    """Domains whose module is present in this installation."""
    out = []
    for name, target in DOMAINS.items():
        module = target.split(":")[0]
        if importlib.util.find_spec(module) is not None:
            out.append(name)
    return out


def get_domain(name: str):
    if name not in DOMAINS:
        raise SpecError(f"unknown domain {name!r}; choose one of {', '.join(sorted(DOMAINS))}")
    if name not in _instances:
        module_name, cls_name = DOMAINS[name].split(":")
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as e:
            if e.name == module_name:
                raise SpecError(f"domain {name!r} is not implemented yet in this version of asp-dist; "
                                f"available: {', '.join(available_domains())}") from None
            raise
        _instances[name] = getattr(module, cls_name)()
    return _instances[name]
