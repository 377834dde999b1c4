"""The wheel's build: setuptools', then numba's cache of the kernels compiled into the wheel.

numba compiles a kernel on its first call and caches it beside the source, in ``__pycache__``.
A wheel without that cache made every fresh install, container and replica compile for one to
three minutes before its first answer. So ``build_wheel`` runs the warm-up
(``app.housekeeping.warm_up``: every kernel the service and ``vantage import`` call, in every
signature they call it with) on the wheel's own files, and packs the cache that leaves:

- compiled for the architecture's baseline CPU (``spatial._cpu``): numba keys its cache by CPU
  name and features, and the baseline loads on any host of the architecture;
- tagged for this Python and platform (``cp311-cp311-linux_x86_64``), as compiled wheels are;
- requiring the numba it was compiled with: numba ignores a cache another version wrote.

``pip wheel . --config-settings kernels=none`` builds the plain wheel (seconds, pure Python),
whose installs compile on first use instead. Editable installs are setuptools' own.
"""

from __future__ import annotations

import base64
import hashlib
import importlib.metadata
import os
import re
import subprocess
import sys
import sysconfig
import tempfile
import tomllib
import zipfile
from pathlib import Path

from setuptools import build_meta
from setuptools.build_meta import *  # noqa: F403 (setuptools' hooks, but for the two below)

# numba's index and data files, and the list of the kernels the warm-up called, which an
# installed start loads by (``app.housekeeping.Listed`` and its ``LISTED_SUFFIX``)
CACHE_SUFFIXES = (".nbi", ".nbc", ".kernels")


def get_requires_for_build_wheel(config_settings: dict | None = None) -> list[str]:
    """setuptools, and what the warm-up imports: the project's own dependencies."""
    required = build_meta.get_requires_for_build_wheel(config_settings)
    if _kernels(config_settings):
        project = tomllib.loads(Path("pyproject.toml").read_text())["project"]
        required += project["dependencies"]
    return required


def build_wheel(
    wheel_directory: str, config_settings: dict | None = None, metadata_directory: str | None = None
) -> str:
    name = build_meta.build_wheel(wheel_directory, config_settings, metadata_directory)
    if not _kernels(config_settings):
        return name
    plain = Path(wheel_directory) / name
    with tempfile.TemporaryDirectory(prefix="vantage-wheel-") as scratch:
        with zipfile.ZipFile(plain) as wheel:
            wheel.extractall(scratch)
        caches = _compile(Path(scratch))
        compiled = _repack(plain, Path(scratch), caches)
    plain.unlink()
    return compiled.name


def _kernels(config_settings: dict | None) -> bool:
    choice = (config_settings or {}).get("kernels", "cached")
    if choice not in ("cached", "none"):
        raise ValueError(f"--config-settings kernels={choice!r}: use 'cached' (the default) or 'none'")
    return choice == "cached"


def _compile(root: Path) -> list[Path]:
    """Run the warm-up on the wheel's files at ``root``; the cache files it wrote there."""
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "NUMBA_CPU_FEATURES")}
    # The wheel's files first; then what was there (pip's isolated build puts its packages on
    # the path through a sitecustomize found on PYTHONPATH)
    path = os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")]))
    env |= {"PYTHONPATH": path, "NUMBA_CPU_NAME": "generic", "PYTHONDONTWRITEBYTECODE": "1"}
    print("compiling the kernels into the wheel (a minute or two) ...", file=sys.stderr, flush=True)
    warm_up = (
        "import sys, app, spatial\n"
        "assert all(m.__file__.startswith(sys.argv[1]) for m in (app, spatial)), 'not the wheel files'\n"
        "from app.housekeeping import warm_up\n"
        "warm_up()\n"
    )
    subprocess.run([sys.executable, "-c", warm_up, str(root)], cwd=root, env=env, check=True)
    caches = sorted(p for p in root.rglob("__pycache__/*") if p.suffix in CACHE_SUFFIXES)
    if not caches:
        raise RuntimeError("the warm-up compiled no kernel into the wheel's __pycache__ directories")
    return caches


def _repack(plain: Path, root: Path, caches: list[Path]) -> Path:
    """The wheel at ``plain`` with ``caches`` added, its tag and numba's requirement made exact."""
    python = f"cp{sys.version_info.major}{sys.version_info.minor}"
    tag = f"{python}-{python}-{re.sub(r'[-.]', '_', sysconfig.get_platform())}"
    project, version = plain.name.split("-")[:2]
    compiled = plain.with_name(f"{project}-{version}-{tag}.whl")
    numba = importlib.metadata.version("numba")
    records: list[str] = []
    with zipfile.ZipFile(plain) as source, zipfile.ZipFile(compiled, "w", zipfile.ZIP_DEFLATED) as wheel:
        record_name = next(n for n in source.namelist() if n.endswith(".dist-info/RECORD"))
        for info in source.infolist():
            if info.filename == record_name:
                continue
            data = source.read(info)
            if info.filename.endswith(".dist-info/WHEEL"):
                data = re.sub(rb"(?m)^Tag: .*$", f"Tag: {tag}".encode(), data)
                data = data.replace(b"Root-Is-Purelib: true", b"Root-Is-Purelib: false")
            elif info.filename.endswith(".dist-info/METADATA"):
                data = re.sub(
                    rb"(?m)^Requires-Dist: numba\b[^;\n]*", f"Requires-Dist: numba=={numba}".encode(), data
                )
            wheel.writestr(info, data)
            records.append(_record(info.filename, data))
        for path in caches:
            arcname = path.relative_to(root).as_posix()
            data = path.read_bytes()
            wheel.writestr(arcname, data)
            records.append(_record(arcname, data))
        records.append(f"{record_name},,")
        wheel.writestr(record_name, "\n".join(records) + "\n")
    return compiled


def _record(name: str, data: bytes) -> str:
    digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
    return f"{name},sha256={digest},{len(data)}"
