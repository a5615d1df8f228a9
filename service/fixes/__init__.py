"""Fix requests, single or batched: one road, :func:`service.fixes.pipeline.fix_results`.

decode (:mod:`~service.fixes.decode`) -> read into one core batch (:mod:`~service.fixes.read`, under the rules
of :mod:`~service.fixes.rules`) -> solve (:func:`core.estimators.iter_solutions`) -> summarise
(:mod:`core.fix_summary`) -> write (:mod:`~service.fixes.write`). This package imports
nothing itself, so that importing one step loads only what that step needs.
"""
