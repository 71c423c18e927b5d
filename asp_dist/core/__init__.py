"""What a domain plugin is written against, below everything that trains or sweeps: the domain contract
(contract.py: Domain, Knob, CellSpec, check_domain) and the registry that finds every domain by name through
the ``asp_dist.domains`` entry points (registry.py). The built-in domains live above, in asp_dist.domains."""
