"""Request and response models of the HTTP contract (API.md), by job: the shapes all share
(:mod:`~service.schemas.common`), fixes (:mod:`~service.schemas.fixes`) and planning
(:mod:`~service.schemas.planning`), named here too, so that ``schemas.FixRequest`` reads the same
wherever it is used; and the sessions' (:mod:`~service.schemas.sessions`), used by module, since they
load the tracking core. Every model is defined once, in its module.
"""

from service.schemas.common import *  # noqa: F403
from service.schemas.fixes import *  # noqa: F403
from service.schemas.planning import *  # noqa: F403
