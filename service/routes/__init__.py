"""Every router of the service, in the order they are mounted."""

from service.routes import fixes, health

ROUTERS = [health.router, fixes.router]
