"""The package's import graph follows the flow of the work, one way only:

    plugins → cli → study → analysis → sweep → tracking → results → training → spec → core → data → foundations

(foundations: errors, hashing, nn, fsutil, knobs, plugins, method_registry, machine; `cli` is the entry point
asp_dist.cli and its commands, asp_dist.commands.*, which never import it back; `study` the drivers that grow a
sweep by what its statistics say, asp_dist.study; `core` is what a domain plugin is
written against, asp_dist.core: the domain contract and registry). A module may import from its own stage or any
stage below it, never from above, and no two modules import each other, directly or through others.
Imports under `if TYPE_CHECKING:` (annotations only) count as imports: an annotation that points up a stage
is an edge of the design all the same (the domain contract describes the spec it reads, core.contract.CellSpec,
instead of importing spec.py, which is built from the domains' knobs).

The built-in domains (asp_dist.domains and its packages: card, game, trainers) are plugins as a third-party one
is: they stand above everything and may use any of it (the contract, the trainers' shared pieces, the
figures' helpers, the spec), and no module outside them imports them: the core finds them through entry
points (asp_dist.core.registry), so no grimp edge leads to them."""

from __future__ import annotations

import grimp
import pytest

STAGES = ["cli", "study", "analysis", "sweep", "tracking", "results", "training", "spec", "core", "data"]
FOUNDATIONS = ["errors", "hashing", "nn", "fsutil", "knobs", "plugins", "method_registry", "machine"]
PLUGIN_STAGE = -2  # a built-in domain's package: above every stage
SAME_STAGE = {"commands": "cli"}  # asp_dist.commands.*: the subcommands that asp_dist.cli assembles


@pytest.fixture(scope="module")
def graph():
    return grimp.build_graph("asp_dist", exclude_type_checking_imports=False)


def is_builtin_domain(module: str) -> bool:
    return module == "asp_dist.domains" or module.startswith("asp_dist.domains.")


def stage_of(module: str) -> int:
    """The module's place in the flow (lower: later in the flow, may import more); -1 outside it."""
    if is_builtin_domain(module):
        return PLUGIN_STAGE
    part = module.split(".")[1] if module.count(".") else ""
    part = SAME_STAGE.get(part, part)
    if part in STAGES:
        return STAGES.index(part)
    if part in FOUNDATIONS:
        return len(STAGES)
    return -1  # the package root (__version__) and __main__: outside the stages


def test_every_module_has_a_stage(graph):
    lost = sorted(m for m in graph.modules if m.count(".") and stage_of(m) == -1 and not m.endswith("__main__"))
    assert not lost, f"modules outside the stages of the flow: {lost}"


def test_no_import_goes_up_a_stage(graph):
    upward = []
    for module in graph.modules:
        for imported in graph.find_modules_directly_imported_by(module):
            if stage_of(module) != -1 and stage_of(imported) != -1 and stage_of(imported) < stage_of(module):
                upward.append(f"{module} -> {imported}")
    assert not upward, "imports from a later stage back into an earlier one:\n" + "\n".join(sorted(upward))


def test_foundations_import_no_stage(graph):
    bad = [f"{m} -> {i}" for m in graph.modules if stage_of(m) == len(STAGES)
           for i in graph.find_modules_directly_imported_by(m) if 0 <= stage_of(i) < len(STAGES) or is_builtin_domain(i)]
    assert not bad, bad


def test_no_import_cycles(graph):
    cycles = []
    for module in sorted(graph.modules):
        for imported in graph.find_modules_directly_imported_by(module):
            if imported != module and graph.chain_exists(importer=imported, imported=module):
                cycles.append(f"{module} <-> {imported}")
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


def test_commands_do_not_import_the_entry_point(graph):
    """asp_dist.cli assembles the commands (build_parser) and runs one (main); a command needs neither."""
    bad = sorted(m for m in graph.modules if m.startswith("asp_dist.commands")
                 and graph.chain_exists(importer=m, imported="asp_dist.cli"))
    assert not bad, f"command modules that import asp_dist.cli: {bad}"


# asp_dist knows domains only through the registry (entry points) and the contract: no module outside
# asp_dist/domains/ imports a built-in domain, not even for annotations (a plugin must be able to stand where
# the built-ins stand).
def test_nothing_imports_a_builtin_domain(graph):
    bad = [f"{m} -> {i}" for m in sorted(graph.modules) if not is_builtin_domain(m)
           for i in graph.find_modules_directly_imported_by(m) if is_builtin_domain(i)]
    assert not bad, "modules import a built-in domain:\n" + "\n".join(bad)


def test_a_domain_imports_no_other_domain(graph):
    """Each built-in domain stands alone, as a plugin does: what two domains share lives in the core."""

    def package(module: str) -> str:
        return ".".join(module.split(".")[:3])

    bad = [f"{m} -> {i}" for m in sorted(graph.modules) if is_builtin_domain(m)
           for i in graph.find_modules_directly_imported_by(m) if is_builtin_domain(i) and package(i) != package(m)]
    assert not bad, "domains import each other:\n" + "\n".join(bad)


def test_a_module_over_500_lines_says_why():
    """The project keeps modules under 500 lines; one that is longer says in its docstring why it stays whole."""
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "asp_dist"
    silent = []
    for path in sorted(root.rglob("*.py")):
        text = path.read_text()
        if text.count("\n") > 500 and "over the project's 500" not in (ast.get_docstring(ast.parse(text)) or ""):
            silent.append(str(path.relative_to(root.parent)))
    assert not silent, f"modules over 500 lines whose docstring does not say why: {silent}"
