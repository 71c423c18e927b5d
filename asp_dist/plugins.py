"""Plugins: components found through a Python entry-point group, the built-in ones included.

asp-dist registers its own domains (group ``asp_dist.domains``) and methods (``asp_dist.methods``) in its
pyproject.toml exactly as another package registers its own, so a built-in has no privilege a plugin lacks.
A group is read once, on first use, never when this module is imported. `asp_dist.spec` reads the domains'
group when it is first imported (it makes their knobs fields of CellSpec), so every command that imports
it, `asp-dist --help` included, loads every domain's card; cards import no torch (asp_dist.core.contract).

A plugin that cannot be loaded or fails its group's declaration check, or whose name another package
registers too, is *set aside*: the others work as before, and asking for it gives one line naming the plugin
and what is wrong (`Registry.lookup`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points
from typing import Generic, TypeVar

from asp_dist.errors import SpecError

T = TypeVar("T")


@dataclass(frozen=True)
class Plugin:
    """Where a registered component comes from: its entry point and the distribution that ships it."""

    name: str
    value: str  # "package.module:attribute"
    distribution: str
    version: str

    def describe(self) -> str:
        return f"{self.name!r} ({self.value}, from {self.distribution} {self.version})"


class Registry(Mapping[str, T], Generic[T]):
    """name -> component of every plugin of one entry-point group that loaded and passed `check`, by name.

    kind   what a component is called in messages ("domain", "method")
    load   the loaded entry point's object -> the component (e.g. a class -> an instance)
    check  (component, registered name) -> what is wrong with its declaration (empty: nothing)
    """

    def __init__(self, group: str, kind: str, load: Callable[[object], T],
                 check: Callable[[T, str], list[str]]) -> None:
        self.group, self.kind, self._make, self._check = group, kind, load, check
        self._found: dict[str, T] | None = None
        self.plugins: dict[str, Plugin] = {}
        self.set_aside: dict[str, str] = {}  # plugin name -> the one line that says why

    def _load(self) -> dict[str, T]:
        if self._found is None:
            found: dict[str, T] = {}
            eps = sorted(entry_points(group=self.group), key=lambda e: (e.name, _dist(e)[0]))
            names = [ep.name for ep in eps]
            for ep in eps:
                plugin = Plugin(ep.name, ep.value, *_dist(ep))
                if names.count(ep.name) > 1:  # which package would win is an accident of installation: neither
                    others = [Plugin(o.name, o.value, *_dist(o)).describe() for o in eps if o.name == ep.name]
                    self.set_aside[ep.name] = (f"{self.kind} {ep.name!r} is registered by {len(others)} plugins: "
                                               f"{'; '.join(others)}; uninstall all but one")
                    continue
                self.plugins[ep.name] = plugin
                component, problem = self._instantiate(ep, plugin)
                if problem is not None:
                    self.set_aside[ep.name] = problem
                else:
                    found[ep.name] = component
            self._found = found
        return self._found

    def _instantiate(self, ep: EntryPoint, plugin: Plugin) -> tuple[T | None, str | None]:
        where = f"{self.kind} plugin {plugin.describe()}"
        try:
            component = self._make(ep.load())
        except Exception as err:  # a plugin's import error must not take the others down
            first = str(err).strip().splitlines()[0] if str(err).strip() else ""
            return None, f"{where} cannot be loaded: {type(err).__name__}{': ' + first if first else ''}"
        problems = self._check(component, ep.name)
        return (None, f"{where}: {problems[0]}") if problems else (component, None)

    def refuse(self, name: str, problem: str) -> None:
        """Set a loaded component aside after the fact (e.g. a domain knob that collides with a core field)."""
        self._load().pop(name, None)
        plugin = self.plugins.get(name)
        self.set_aside[name] = f"{self.kind} plugin {plugin.describe() if plugin else repr(name)}: {problem}"

    def problems(self) -> dict[str, str]:
        """Plugins that were set aside, with the one line that says why."""
        self._load()
        return dict(self.set_aside)

    def lookup(self, name: str) -> T:
        """The component, or SpecError: the set-aside line, or the names to choose from."""
        found = self._load()
        if name in found:
            return found[name]
        if name in self.set_aside:
            raise SpecError(self.set_aside[name])
        if not found and not self.set_aside:
            raise SpecError(f"no {self.kind} is registered (entry-point group {self.group!r} is empty): install "
                            f"asp-dist with `pip install -e .` (scripts/install.sh) so that its entry points are known")
        raise SpecError(f"unknown {self.kind} {name!r}; choose one of {', '.join(sorted(found))}")

    def __getitem__(self, name: str) -> T:
        return self._load()[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._load())

    def __len__(self) -> int:
        return len(self._load())

    def __repr__(self) -> str:
        return f"{self.kind.upper()}S({', '.join(self._load())})"


def _dist(ep: EntryPoint) -> tuple[str, str]:
    dist = getattr(ep, "dist", None)
    return (dist.metadata["Name"], dist.version) if dist is not None else ("an unknown distribution", "?")
