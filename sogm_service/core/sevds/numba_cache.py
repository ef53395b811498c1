"""Where numba keeps the compiled SEVDS kernels (``cache=True``), chosen before numba loads.

numba caches next to the source (``core/__pycache__``) when that is writable, else in the
user's cache directory; in a read-only install without a writable home (a hardened systemd
unit: ``ProtectSystem=strict``, ``ProtectHome=true``) neither works and the ``@njit`` decorator
itself fails (``cannot cache function ...: no locator available``).  :func:`ensure_cache_dir`
sets ``NUMBA_CACHE_DIR`` when it is unset and the package directory is not writable, to the
first writable of: systemd's ``$CACHE_DIRECTORY`` (``CacheDirectory=`` in the unit),
``$XDG_CACHE_HOME`` or ``~/.cache``, then the temporary directory (per user); each gets a
``sogm-service/numba`` (temp: ``sogm-service-numba-<uid>``) subdirectory.  An explicit
``NUMBA_CACHE_DIR`` always wins.
"""

from __future__ import annotations

import os
import sys
import tempfile
from collections.abc import Mapping
from pathlib import Path

_HERE = Path(__file__).resolve().parent


def _can_write(path: Path) -> bool:
    """True when a file can be created in the directory ``path`` (tried, not guessed: a
    read-only mount or a sandbox says no even to root)."""
    try:
        with tempfile.TemporaryFile(dir=path):
            return True
    except OSError:
        return False


def _writable_dir(path: Path) -> bool:
    """True when ``path`` exists (or can be created) and files can be written in it."""
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return False
    return _can_write(path)


def choose_cache_dir(package_dir: Path, env: Mapping[str, str]) -> Path | None:
    """The directory numba should cache in, or ``None`` when numba's default (beside the
    source, ``package_dir/__pycache__``) works or ``NUMBA_CACHE_DIR`` is already set."""
    if env.get("NUMBA_CACHE_DIR"):
        return None
    pycache = package_dir / "__pycache__"
    if _can_write(pycache) if pycache.is_dir() else _can_write(package_dir):
        return None  # numba caches beside the source
    candidates: list[Path] = []
    if env.get("CACHE_DIRECTORY"):  # systemd CacheDirectory= (may list several, ':'-separated)
        candidates.append(Path(env["CACHE_DIRECTORY"].split(":")[0]) / "numba")
    xdg = env.get("XDG_CACHE_HOME")
    if xdg:
        candidates.append(Path(xdg) / "sogm-service" / "numba")
    home = env.get("HOME")
    if home:
        candidates.append(Path(home) / ".cache" / "sogm-service" / "numba")
    uid = os.getuid() if hasattr(os, "getuid") else 0
    candidates.append(Path(tempfile.gettempdir()) / f"sogm-service-numba-{uid}")
    for path in candidates:
        if _writable_dir(path):
            return path
    return None  # nothing writable: numba's own error says why


def ensure_cache_dir() -> Path | None:
    """Set ``NUMBA_CACHE_DIR`` when it is needed (see the module docstring); returns the
    directory set, if any.  Call before numba is imported (if numba already is, its config
    is reloaded)."""
    chosen = choose_cache_dir(_HERE, os.environ)
    if chosen is not None:
        os.environ["NUMBA_CACHE_DIR"] = str(chosen)
        if "numba" in sys.modules:
            from numba.core import config

            config.reload_config()
    return chosen
