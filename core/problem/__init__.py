"""A localisation problem: stations and measurements placed in their exact common ENU frame, one or many.

``frame.py`` holds the frame (:class:`~core.problem.frame.CommonFrame`), the points and the problem record
every estimator reads (:class:`~core.problem.frame.Problem`), below everything else here; ``build.py``
checks a caller's stations and measurements and builds one problem (:func:`~core.problem.build.build_problem`);
``batch.py`` holds many problems padded to common sizes (:class:`~core.problem.batch.ProblemBatch`), which
``batch_build.py`` builds from flat inputs in compiled passes, and whose masks and geometry come from the
compiled passes of ``batch_kernels.py``. A single problem is a batch of one, so it gets the same bits alone
and in a batch. This package imports nothing itself.
"""
