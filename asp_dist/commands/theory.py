"""`asp-dist theory`: the paper's policy-space pruning of the adversary, exact and in Stirling's form."""

from __future__ import annotations

import argparse
import json
import math

from asp_dist.commands.common import int_between
from asp_dist.errors import SpecError


def cmd_theory(args: argparse.Namespace) -> int:
    from asp_dist.analysis import theory

    if args.probs is not None and args.skew is not None:
        raise SpecError("give either --probs or --skew, not both")
    probs = None
    if args.probs is not None:
        probs = parse_probs(args.probs, args.actions)
    elif args.skew is not None:
        if not math.isfinite(args.skew):
            raise SpecError(f"--skew must be a finite number, got {args.skew}")
        try:
            probs = theory.skew_probs(args.actions, args.skew)
        except (OverflowError, ZeroDivisionError):
            raise SpecError(f"--skew {args.skew} is too large for {args.actions} actions") from None
    try:
        result = theory.analyse(args.states, args.actions, probs)
    except (ValueError, OverflowError, ZeroDivisionError) as e:
        raise SpecError(str(e) or type(e).__name__) from None
    if args.json:
        print(json.dumps({**result.__dict__, "fraction_kept": result.fraction_kept}, indent=1))
        return 0
    print(f"S = {result.states} states, A = {result.actions} actions, distribution: {result.distribution}")
    print(f"  ln(all policies)  = S ln A                 = {result.log_all_policies:12.4f}")
    print(f"  ln(adversarially allowed) = ln multinomial = {result.log_adversarial_policies:12.4f}")
    print(f"  log-ratio, exact (lgamma)                  = {result.log_ratio_exact:12.4f}")
    print(f"  log-ratio, Stirling with ½ln(2πn) terms    = {result.log_ratio_stirling:12.4f}")
    if result.log_ratio_big_o is not None:
        print(f"  paper's big-O form ln S − A ln(S/A)        = {result.log_ratio_big_o:12.4f}")
    one_in = math.exp(-result.log_ratio_exact) if -result.log_ratio_exact < 700 else math.inf
    print(f"  fraction of policies kept                  = {result.fraction_kept:.4g}"
          f"  (1 in {one_in:.4g})")
    return 0


def parse_probs(text: str, actions: int) -> list[float]:
    """--probs: one finite, non-negative number per action, not all zero."""
    try:
        probs = [float(p) for p in text.split(",")]
    except ValueError:
        raise SpecError(f"--probs {text!r}: write comma-separated numbers, one per action (e.g. 0.5,0.3,0.2)") \
            from None
    if not all(math.isfinite(p) and p >= 0 for p in probs) or not sum(probs) > 0:
        raise SpecError(f"--probs {text!r}: probabilities must be finite, >= 0 and not all zero")
    if len(probs) != actions:
        raise SpecError(f"--probs gives {len(probs)} probabilities for {actions} actions (--actions)")
    return probs


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("theory", help="policy-space pruning of the adversary (the paper's analysis)")
    p.add_argument("--states", "-S", type=int_between(1), required=True)
    p.add_argument("--actions", "-A", type=int_between(1), required=True)
    p.add_argument("--probs", help="comma-separated action distribution (default uniform)")
    p.add_argument("--skew", type=float, help="p_k ∝ exp(-skew·k), as in the signaling game")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_theory)
