"""Every domain, by name, found through the ``asp_dist.domains`` entry-point group (asp_dist.plugins).

asp-dist's own four domains register in its pyproject.toml exactly as a plugin package registers its
own (docs/extending.md). A plugin that cannot be imported, is not a Domain, registers under another name
than its own, declares a malformed knob or a knob twice, lacks a required metric or channel, or shares its
name with another package's domain, is *set aside*: the other domains work as before, and asking for it
(`get_domain`, a space, `asp-dist check-domain`) gives one line naming the plugin and what is wrong.
`asp_dist.spec` sets aside, the same way, a domain whose knob collides with a core field or another domain's.
"""

from __future__ import annotations

from asp_dist.core.contract import Domain
from asp_dist.plugins import Registry

GROUP = "asp_dist.domains"
REQUIRED_METRICS = ("mixed", "self_play_new", "self_play_base")


def declaration_problems(domain: object, name: str) -> list[str]:
    """What is wrong with what a domain declares, checked without running it (the contract checker,
    contract.check_domain, runs it)."""
    if not isinstance(domain, Domain):
        return [f"it is a {type(domain).__name__}, not an asp_dist.core.contract.Domain"]
    problems = []
    if domain.name != name:
        problems.append(f"it is registered as {name!r} but its Domain.name is {domain.name!r}")
    seen: set[str] = set()
    for knob in domain.knobs:
        problems += knob.problems(name)
        if knob.name in seen:
            problems.append(f"knob {knob.name!r} is declared twice")
        seen.add(knob.name)
    missing = [m for m in REQUIRED_METRICS if m not in domain.metrics]
    if missing:
        problems.append(f"its metrics lack {', '.join(missing)}")
    if not domain.channels:
        problems.append("it declares no convention channel (Domain.channels)")
    return problems


def _instance(obj: object) -> object:
    return obj() if isinstance(obj, type) else obj  # a Domain class (the usual entry point) or an instance


DOMAINS: Registry[Domain] = Registry(GROUP, "domain", _instance, declaration_problems)


def get_domain(name: str) -> Domain:
    return DOMAINS.lookup(name)


def set_aside() -> dict[str, str]:
    """Domain plugins that did not load, with the one line that says why (asp-dist fields warns with them)."""
    return DOMAINS.problems()
