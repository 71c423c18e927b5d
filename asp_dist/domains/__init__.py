"""The built-in domains: the paper's three (particles, vae, levers), the signaling game of its analysis and
the PettingZoo adapter (pettingzoo). Each is a plugin as a third-party package is: it is written against the
contract (asp_dist.core.contract), may use the trainers' shared pieces (asp_dist.training) and the figures'
helpers (asp_dist.analysis), and is found only through its entry point in pyproject.toml
(asp_dist.core.registry); nothing in the package imports it."""
