"""Every router of the service, in the order they are mounted."""

from service.routes import evaluations, fixes, health

ROUTERS = [health.router, fixes.router, evaluations.router]
