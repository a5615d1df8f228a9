"""The locator's mathematics, pure numpy/scipy/numba: nothing here knows about HTTP.

``problem/`` (a localisation problem in its common frame, one or a batch), ``estimators/`` (the solve, the
finisher and the shared machinery; ``estimators/methods/`` one module per method), ``tracking/`` (moving
emitters: session filters, the network tracker, association), ``simulation/`` (scenarios, Monte Carlo and
the papers' figures); beside them the geodesy, measurement models, CRLB, error summaries, coverage maps,
linear algebra, the parallel chunk runner and the compiled kernels' warm-up (``kernels.py``).
"""
