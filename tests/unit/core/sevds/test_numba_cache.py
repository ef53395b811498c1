"""Where numba caches the compiled kernels: a read-only install still gets a usable cache."""

from __future__ import annotations

import tempfile
from pathlib import Path

from sogm_service.core.sevds.numba_cache import choose_cache_dir


def test_numba_cache_dir_for_a_read_only_install(tmp_path: Path) -> None:
    pkg = tmp_path / "pkg"
    (pkg / "__pycache__").mkdir(parents=True)
    assert choose_cache_dir(pkg, {"HOME": str(tmp_path)}) is None  # writable: numba's own
    read_only = Path("/proc/self")  # no file can be created here, not even by root
    env = {"HOME": str(tmp_path / "home"), "XDG_CACHE_HOME": str(tmp_path / "xdg")}
    assert choose_cache_dir(read_only, env) == tmp_path / "xdg" / "sogm-service" / "numba"
    assert choose_cache_dir(read_only, {"HOME": str(tmp_path / "home")}) == \
        tmp_path / "home" / ".cache" / "sogm-service" / "numba"
    assert choose_cache_dir(read_only, {**env, "CACHE_DIRECTORY": str(tmp_path / "sd")}) == \
        tmp_path / "sd" / "numba"  # systemd's CacheDirectory= first
    assert choose_cache_dir(read_only, {**env, "NUMBA_CACHE_DIR": "/x"}) is None  # explicit
    unusable = {"HOME": "/proc/self/nohome", "XDG_CACHE_HOME": "/proc/self/nohome"}
    chosen = choose_cache_dir(read_only, unusable)
    assert chosen is not None and chosen.parent == Path(tempfile.gettempdir())
