"""Every router of the service, in the order they are mounted."""

from service.routes import evaluations, fixes, health

ROUTERS = [health.router, fixes.router, evaluations.router]

from service.routes import batch  # noqa: E402  (the batch path: issue 6)
ROUTERS.append(batch.router)
