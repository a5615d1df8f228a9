"""A frozen copy of the session filters as of commit ed7cbfd (before the step-time rewrite).

Not used by the service. ``tests/core/tracking/test_regression.py`` steps this copy and
``core.tracking`` side by side on fixed scenarios and requires the same numbers to about 1e-12
(relative): the rewrite of the hot path is a change of arithmetic, not of the filter. Only the
imports of the five modules were changed (to point into this package); ``config`` and ``state``
are shared with ``core.tracking``. Do not "fix" anything here: a deliberate change of the filter
shows up as a failure of that test, which is then updated with the reason.
"""
