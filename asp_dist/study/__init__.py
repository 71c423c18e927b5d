"""Studies: drivers that grow sweeps by what their statistics say (asp-dist decide: a registered comparison tested
after each stage of trials, asp_dist.study.decide_run). They stand above the analysis and the sweep machinery,
using both; the commands call them."""
