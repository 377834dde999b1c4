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
    max_items: int = Field(10_000_000, description="items one document may hold (413 beyond)")
    max_stream_rate: float = Field(120.0, description="viewports a stream client may send per second")
    tokens: str = Field("", description="comma-separated bearer tokens that may write; none: loopback only")
    tokens_file: Path | None = Field(None, description="a file of tokens, one a line, added to `tokens`")
    read_token: bool = Field(False, description="reads need a token too")
    cors_origins: str = Field("", description="comma-separated origins allowed by CORS (none by default)")

    def token_list(self) -> list[bytes]:
        """Every configured token, as bytes for the constant-time comparison."""
        lines = self.tokens.split(",")
        if self.tokens_file is not None:
            lines += self.tokens_file.read_text().splitlines()
        return [t.strip().encode() for t in lines if t.strip()]


@lru_cache
def get_settings() -> Settings:
    """The process's settings; tests override this dependency."""
    return Settings()
