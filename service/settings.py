"""Service settings from the environment (prefix ``PASSIVE_LOCATOR_``)."""

from __future__ import annotations

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """Runtime configuration.

    Attributes
    ----------
    store : str
        Session store URL: ``sqlite:///path`` (embedded default) or
        ``redis://host:port/db``.
    max_body_bytes : int
        Larger request bodies get 413.
    api_keys : list of str
        Bearer keys; empty disables authentication.
    rate_limit_per_s : float
        Sustained requests per second per client (key or address); 0 disables.
    rate_limit_burst : int
    cors_allow_origins : list of str
        Origins whose browser pages may call the API (a JSON list, ``["*"]`` for any); empty (the
        default) sends no CORS headers, so browsers refuse cross-origin calls.
    """

    model_config = SettingsConfigDict(env_prefix="PASSIVE_LOCATOR_", extra="ignore")

    store: str = "sqlite:///./var/sessions.db"
    max_body_bytes: int = Field(32 * 1024 * 1024, gt=0)
    api_keys: list[str] = Field(default_factory=list)
    rate_limit_per_s: float = Field(0.0, ge=0.0)
    rate_limit_burst: int = Field(100, ge=1)
    log_level: str = "info"
    cors_allow_origins: list[str] = Field(default_factory=list)
