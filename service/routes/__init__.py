"""Every router of the service, in the order they are mounted."""

from service.routes import coverage, evaluations, fixes, health, sessions

ROUTERS = [health.router, fixes.router, coverage.router, evaluations.router, sessions.router]

from service.routes import batch  # noqa: E402  (the batch path: issue 6)

ROUTERS.append(batch.router)
