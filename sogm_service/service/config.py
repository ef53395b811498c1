"""Service configuration: a TOML file validated by pydantic; every field has a sane default.

``sogm-service serve`` with no file serves map ``default`` at 5 cm in frame ``map``, listens for
ISMs on ``ism/**`` and poses on ``pose/**``, keeps tiles in memory only, and runs Zenoh as a peer
with multicast scouting off.  ``deploy/sogm-service.toml`` documents every field.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from sogm_service.core import logodds
from sogm_service.wire.messages import GeodeticFix, InterpName


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class MapSettings(_Section):
    name: Annotated[str, Field(pattern=r"^[A-Za-z0-9_\-]+$")] = "default"
    frame: str = "map"
    resolution: Annotated[float, Field(gt=0, le=100)] = 0.05
    tile_size: int = 256
    eps0: Annotated[float, Field(ge=logodds.MIN_EPS0, lt=0.5)] = logodds.DEFAULT_EPS0
    datum: GeodeticFix | None = None

    @field_validator("tile_size")
    @classmethod
    def _power_of_two(cls, v: int) -> int:
        if v < 16 or v > 4096 or v & (v - 1):
            raise ValueError("tile_size must be a power of two between 16 and 4096")
        return v


class MatchingSettings(_Section):
    """ORB scan matching of this source's ISMs (paper section III-C.2)."""

    mode: Literal["off", "correct", "report"] = "off"
    on_failure: Literal["fuse", "reject"] = "fuse"
    layer: str | None = None  # map layer to match against; default the ISM's own layer
    model: Literal["similarity", "homography"] = "similarity"
    # 6: measured on the Intel log (``sogm-service eval matching``): 65 % of perturbed scans
    # accepted, 0.05 % of those grossly wrong; 12 accepts 31 % (README trade-off table).
    min_inliers: Annotated[int, Field(ge=4)] = 6
    max_translation_m: Annotated[float, Field(gt=0)] = 1.0
    max_rotation_deg: Annotated[float, Field(gt=0, le=180)] = 15.0
    # Map beyond the reach of the largest accepted correction (MatchParams.window_extra);
    # measured: 1 m more changes nothing on the Intel log, so none by default.
    margin_m: Annotated[float, Field(ge=0)] = 0.0


class IsmSource(_Section):
    """One ISM key expression and how its ISMs are treated."""

    key_expr: str = "ism/**"
    interp: InterpName = "biodds"
    matching: MatchingSettings = MatchingSettings()


class TileSettings(_Section):
    hysteresis_m: Annotated[float, Field(ge=0)] = 1.0
    roi_radius_tiles: Annotated[int, Field(ge=0, le=16)] = 1
    replicate_on_start: bool = False


class StorageSettings(_Section):
    directory: Path | None = None
    checkpoint_interval_s: Annotated[float, Field(gt=0)] = 10.0
    memory_budget_mb: Annotated[float, Field(gt=0)] = 1024.0


class LimitSettings(_Section):
    max_ism_cells: Annotated[int, Field(gt=0)] = 4096 * 4096
    max_ism_tiles: Annotated[int, Field(gt=0)] = 1024
    max_payload_bytes: Annotated[int, Field(gt=0)] = 128 * 1024 * 1024
    max_query_cells: Annotated[int, Field(gt=0)] = 4096 * 4096
    queue_size: Annotated[int, Field(ge=1, le=100000)] = 64
    queue_policy: Literal["lossless", "latest"] = "lossless"


class ZenohSettings(_Section):
    mode: Literal["peer", "client", "router"] = "peer"
    listen: list[str] = []
    connect: list[str] = []
    config_file: Path | None = None
    multicast_scouting: bool = False


class ServiceConfig(_Section):
    map: MapSettings = MapSettings()
    ism: list[IsmSource] = [IsmSource()]
    pose_keys: list[str] = ["pose/**"]
    prefix: Annotated[str, Field(pattern=r"^[A-Za-z0-9_\-/]+$")] = "sogm"
    tiles: TileSettings = TileSettings()
    storage: StorageSettings = StorageSettings()
    limits: LimitSettings = LimitSettings()
    zenoh: ZenohSettings = ZenohSettings()
    log_level: Literal["debug", "info", "warning", "error"] = "info"

    @field_validator("ism")
    @classmethod
    def _at_least_one(cls, v: list[IsmSource]) -> list[IsmSource]:
        if not v:
            raise ValueError("at least one ISM key expression is needed")
        return v

    def key(self, *parts: str) -> str:
        """A key under ``<prefix>/<map>/``."""
        return "/".join([self.prefix.strip("/"), self.map.name, *parts])

    def query_cell_limit(self) -> int:
        return self.limits.max_query_cells

    @property
    def tile_budget(self) -> int:
        """How many full tiles of 8 layers fit the memory budget (for information)."""
        per_tile = 8 * self.map.tile_size ** 2 * 2
        return max(1, math.floor(self.storage.memory_budget_mb * 1e6 / per_tile))


class ConfigError(ValueError):
    """A configuration file that cannot be used: says which field and why."""


def load_config(path: Path | None) -> ServiceConfig:
    """Read and validate a TOML config; ``None`` gives the defaults."""
    if path is None:
        return ServiceConfig()
    try:
        raw = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"cannot read config {path}: {exc.strerror}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"config {path} is not valid TOML: {exc}") from None
    try:
        return ServiceConfig.model_validate(raw)
    except ValidationError as exc:
        lines = [f"{'.'.join(str(p) for p in e['loc']) or '<root>'}: {e['msg']}"
                 for e in exc.errors(include_url=False)]
        raise ConfigError(f"invalid config {path}:\n  " + "\n  ".join(lines)) from None
