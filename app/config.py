"""Settings, read from the environment with the prefix ``VANTAGE_``."""

from functools import lru_cache
from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

__all__ = ["Settings", "get_settings"]


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="VANTAGE_")

    data_dir: Path = Field(Path("./data"), description="where the SQLite store lives")
    host: str = "127.0.0.1"
    port: int = 8000
    max_body_bytes: int = Field(1 << 30, description="largest import body (413 beyond)")
    max_line_bytes: int = Field(64 << 10, description="longest NDJSON line (422 beyond)")
    max_data_bytes: int = Field(4 << 10, description="largest `data` object of one item, as JSON")
    default_limit: int = Field(10_000, description="items per response when the client sets no limit")
    max_limit: int = Field(100_000, description="items per response, whatever the client asks")


@lru_cache
def get_settings() -> Settings:
    """The process's settings; tests override this dependency."""
    return Settings()
