"""Every domain, by name, found through the ``asp_dist.domains`` entry-point group.

asp-dist's own four domains register in its pyproject.toml exactly as a plugin package registers its
own (docs/extending.md), so a built-in has no privilege a plugin lacks. The group is read once, on
first use (not at import: `asp-dist --help` never loads a domain).

A plugin that cannot be imported, is not a Domain, registers under another name than its own, declares
a malformed knob or a knob twice, or shares its name with another package's domain, is *set aside*: the
other domains work as before, and asking for it (`get_domain`, a space, `asp-dist check-domain`) gives
one line naming the plugin and what is wrong. `asp_dist.spec` sets aside, the same way, a domain whose
knob collides with a core field or with another domain's knob.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points

from asp_dist.domains.contract import Domain
from asp_dist.errors import SpecError

GROUP = "asp_dist.domains"
REQUIRED_METRICS = ("mixed", "self_play_new", "self_play_base")


@dataclass(frozen=True)
class Plugin:
    """Where a registered domain comes from: its entry point and the distribution that ships it."""

    name: str
    value: str  # "package.module:Class"
    distribution: str
    version: str

    def describe(self) -> str:
        return f"{self.name!r} ({self.value}, from {self.distribution} {self.version})"


class _Registry(Mapping[str, Domain]):
    """name -> Domain of every plugin that loaded and passed the declaration checks, sorted by name."""

    def __init__(self) -> None:
        self._domains: dict[str, Domain] | None = None
        self.plugins: dict[str, Plugin] = {}
        self.set_aside: dict[str, str] = {}  # plugin name -> the one line that says why

    def _load(self) -> dict[str, Domain]:
        if self._domains is None:
            found: dict[str, Domain] = {}
            eps = sorted(entry_points(group=GROUP), key=lambda e: (e.name, _dist(e)[0]))
            names = [ep.name for ep in eps]
            for ep in eps:
                plugin = Plugin(ep.name, ep.value, *_dist(ep))
                if names.count(ep.name) > 1:  # which package would win is an accident of installation: neither
                    others = [Plugin(o.name, o.value, *_dist(o)).describe() for o in eps if o.name == ep.name]
                    self.set_aside[ep.name] = (f"domain {ep.name!r} is registered by {len(others)} plugins: "
                                               f"{'; '.join(others)}; uninstall all but one")
                    continue
                self.plugins[ep.name] = plugin
                domain, problem = _instantiate(ep, plugin)
                if problem is not None:
                    self.set_aside[ep.name] = problem
                else:
                    found[ep.name] = domain
            self._domains = found
        return self._domains

    def refuse(self, name: str, problem: str) -> None:
        """Set a loaded domain aside (asp_dist.spec: its knobs collide with a core field or another domain's)."""
        self._load().pop(name, None)
        plugin = self.plugins.get(name)
        self.set_aside[name] = f"domain plugin {plugin.describe() if plugin else repr(name)}: {problem}"

    def __getitem__(self, name: str) -> Domain:
        return self._load()[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._load())

    def __len__(self) -> int:
        return len(self._load())

    def __repr__(self) -> str:
        return f"DOMAINS({', '.join(self._load())})"


def _dist(ep: EntryPoint) -> tuple[str, str]:
    dist = getattr(ep, "dist", None)
    return (dist.metadata["Name"], dist.version) if dist is not None else ("an unknown distribution", "?")


def _instantiate(ep: EntryPoint, plugin: Plugin) -> tuple[Domain | None, str | None]:
    """The plugin's Domain, or the one line that says why it is set aside."""
    where = f"domain plugin {plugin.describe()}"
    try:
        obj = ep.load()
        domain = obj() if isinstance(obj, type) else obj
    except Exception as err:  # a plugin's import error must not take the other domains down
        first = str(err).strip().splitlines()[0] if str(err).strip() else ""
        return None, f"{where} cannot be loaded: {type(err).__name__}{': ' + first if first else ''}"
    problems = declaration_problems(domain, ep.name)
    return (None, f"{where}: {problems[0]}") if problems else (domain, None)


def declaration_problems(domain: object, name: str) -> list[str]:
    """What is wrong with what a domain declares, checked without running it (the contract checker,
    contract.check_domain, runs it)."""
    if not isinstance(domain, Domain):
        return [f"it is a {type(domain).__name__}, not an asp_dist.domains.contract.Domain"]
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


DOMAINS = _Registry()


def get_domain(name: str) -> Domain:
    try:
        return DOMAINS[name]
    except KeyError:
        pass
    if name in DOMAINS.set_aside:
        raise SpecError(DOMAINS.set_aside[name])
    if not DOMAINS and not DOMAINS.set_aside:
        raise SpecError(f"no domain is registered (entry-point group {GROUP!r} is empty): install asp-dist with "
                        f"`pip install -e .` (scripts/install.sh) so that its entry points are known")
    raise SpecError(f"unknown domain {name!r}; choose one of {', '.join(sorted(DOMAINS))}")


def set_aside() -> dict[str, str]:
    """Plugins that did not load, with the one line that says why (asp-dist fields warns with them)."""
    DOMAINS._load()
    return dict(DOMAINS.set_aside)
