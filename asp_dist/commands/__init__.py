"""The subcommands of `asp-dist`, one module per command (or small group), each with its flags beside its code.

Each module has `add_parser(sub)`, which registers its subcommand(s) on the `asp-dist` parser with their flags
and sets `func` to its `cmd_*` function; asp_dist.cli assembles them (build_parser) and runs one (main).
A command module imports only light modules at the top (no torch, Ray or the analysis: those are imported
inside the command that needs them), so `--help` and the commands that only read stay fast
(tests/test_cli_imports.py). Commands never import asp_dist.cli (tests/test_architecture.py).
"""
