"""asp-dist: Ray-distributed sweeps of PC, OSP and ASP for adopting social conventions."""

__version__ = "0.1.0"
