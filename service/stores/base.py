"""The session-store interface."""

from __future__ import annotations

from abc import ABC, abstractmethod


class SessionStore(ABC):
    """Durable storage of session records (implemented by the sessions work).

    Attributes
    ----------
    kind : str
        ``"sqlite"`` or ``"redis"``, reported by ``/readyz``.
    """

    kind: str

    @abstractmethod
    def ping(self) -> None:
        """Raise if the backend is unreachable."""

    @abstractmethod
    def close(self) -> None:
        """Release connections."""
