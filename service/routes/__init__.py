"""Every router of the service, in the order they are mounted."""

from service.routes import batch, coverage, evaluations, fixes, health, sessions

ROUTERS = [health.router, fixes.router, coverage.router, evaluations.router, sessions.router, batch.router]
