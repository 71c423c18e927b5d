"""The package's import graph follows the flow of the work, one way only:

    cli → analysis → sweep → results → training → spec → domains → data → foundations

(foundations: errors, hashing, nn, fsutil, knobs, plugins, method_registry). A module may import from its own stage or any
stage below it, never from above, and no two modules import each other, directly or through
others. Imports under `if TYPE_CHECKING:` are annotations only and are not counted."""

from __future__ import annotations

import grimp
import pytest

STAGES = ["cli", "analysis", "sweep", "results", "training", "spec", "domains", "data"]
FOUNDATIONS = ["errors", "hashing", "nn", "fsutil", "knobs", "plugins", "method_registry"]


@pytest.fixture(scope="module")
def graph():
    return grimp.build_graph("asp_dist", exclude_type_checking_imports=True)


def stage_of(module: str) -> int:
    part = module.split(".")[1] if module.count(".") else ""
    if part in STAGES:
        return STAGES.index(part)
    if part in FOUNDATIONS:
        return len(STAGES)
    return -1  # the package root (__version__) and __main__: outside the stages


def test_every_module_has_a_stage(graph):
    lost = sorted(m for m in graph.modules if m.count(".") and stage_of(m) < 0 and not m.endswith("__main__"))
    assert not lost, f"modules outside the stages of the flow: {lost}"


def test_no_import_goes_up_a_stage(graph):
    upward = []
    for module in graph.modules:
        for imported in graph.find_modules_directly_imported_by(module):
            if stage_of(module) >= 0 and stage_of(imported) >= 0 and stage_of(imported) < stage_of(module):
                upward.append(f"{module} -> {imported}")
    assert not upward, "imports from a later stage back into an earlier one:\n" + "\n".join(sorted(upward))


def test_foundations_import_no_stage(graph):
    bad = [f"{m} -> {i}" for m in graph.modules if stage_of(m) == len(STAGES)
           for i in graph.find_modules_directly_imported_by(m) if 0 <= stage_of(i) < len(STAGES)]
    assert not bad, bad


def test_no_import_cycles(graph):
    cycles = []
    for module in sorted(graph.modules):
        for imported in graph.find_modules_directly_imported_by(module):
            if imported != module and graph.chain_exists(importer=imported, imported=module):
                cycles.append(f"{module} <-> {imported}")
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


# The core knows domains only through the registry (entry points) and the contract: no core module imports a
# domain's package, not even for annotations (a plugin must be able to stand where the built-ins stand).
CORE = ("asp_dist.spec", "asp_dist.sweep", "asp_dist.results", "asp_dist.analysis", "asp_dist.cli")
DOMAIN_CORE = ("asp_dist.domains", "asp_dist.domains.contract", "asp_dist.domains.registry")


def test_the_core_imports_no_domain_package():
    graph = grimp.build_graph("asp_dist", exclude_type_checking_imports=False)
    bad = [f"{m} -> {i}" for m in sorted(graph.modules) if m.startswith(CORE)
           for i in graph.find_modules_directly_imported_by(m)
           if i.startswith("asp_dist.domains") and i not in DOMAIN_CORE]
    assert not bad, "core modules import a domain:\n" + "\n".join(bad)
