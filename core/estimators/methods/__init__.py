"""The estimators, one module per method (the registered ``method`` names of the API).

``ml.py`` (maximum likelihood, the reference), ``orthogonal_vector.py`` (``ove``, ``eove``,
``weighted_eove``), ``pseudolinear.py`` (``ple3d``, ``ws3d``), ``total_least_squares.py`` (``tls``,
``ctls``), ``taylor_series.py`` (``taylor_wls``), ``line_of_sight_intersection.py`` (``los_intersection``)
and ``angle_range.py`` (``angle_range``). Each registers its estimators with
:func:`core.estimators.base.register`; what they share (the registry, the finisher, the
Levenberg-Marquardt iteration, losses, starting points, ties) is in :mod:`core.estimators` itself, which
imports every module here so that every method is registered. This package imports nothing itself.
"""
