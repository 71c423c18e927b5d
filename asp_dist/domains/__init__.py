"""The four domains of the paper (and the signaling game of its analysis), each a Domain
(contract.py) registered by name in registry.py."""

from asp_dist.domains.registry import DOMAINS, get_domain

__all__ = ["DOMAINS", "get_domain"]
