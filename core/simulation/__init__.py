"""Simulated measurements and Monte Carlo evaluations, one definition for the tests, the scripts and the CLI.

``scenarios.py`` (the papers' scenarios and the generic scenes), ``measurements.py`` (measurements of a known
target, and the Monte Carlo of the fix methods), ``emitter.py`` and ``tracking.py`` (a moving emitter seen
by one observer, and the session filters' Monte Carlo), ``network.py`` (network tracking scenes),
``multi_emitter.py`` (many emitters, unlabelled bearings) and ``papers.py`` (the five papers' claims,
checked: ``passive-locator reproduce``).
"""
