"""What a benchmark ran on: the lines every report starts with."""

from importlib import metadata

__all__ = ["cpu_model", "versions"]


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            return next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), "unknown")
    except OSError:
        return "unknown"


def versions(packages: tuple[str, ...]) -> str:
    """``"numpy 2.4.6, numba 0.68.1, ..."`` ("missing" for a package not installed)."""

    def version(package: str) -> str:
        try:
            return metadata.version(package)
        except metadata.PackageNotFoundError:
            return "missing"

    return ", ".join(f"{p} {version(p)}" for p in packages)
