"""Settings, read from the environment with the prefix ``VANTAGE_``."""

from functools import lru_cache
from pathlib import Path

from pydantic_settings import BaseSettings, SettingsConfigDict

__all__ = ["Settings", "get_settings"]


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="VANTAGE_")

    data_dir: Path = Path("./data")
    host: str = "127.0.0.1"
    port: int = 8000


@lru_cache
def get_settings() -> Settings:
    """The process's settings; tests override this dependency."""
    return Settings()
