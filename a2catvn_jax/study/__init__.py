"""Experiments: variants x seeds, runs as data, statistics, figures and the results page.

`registry` (the experiments and their variants), `store` (run keys, the stored runs and
what each keeps), `stats` (pure statistics), `report` (figures and markdown), `runner`
(plan, train, evaluate, report: `run_experiment`), `compare` (variants of different
experiments side by side) and `workers` (processes pinned to shares of the cores). The
command line: `python -m a2catvn_jax.experiments --help`.
"""
