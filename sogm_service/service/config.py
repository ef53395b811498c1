"""Service configuration: a TOML file validated by pydantic; every field has a sane default.

``sogm-service serve`` with no file serves map ``default`` at 5 cm in frame ``map``, listens for
ISMs on ``ism/**`` and poses on ``pose/**``, keeps tiles in memory only, and runs Zenoh as a peer
with multicast scouting off.  ``deploy/sogm-service.toml`` documents every field.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from sogm_service.client.session import ZenohSettings
from sogm_service.core import logodds
from sogm_service.core.resample import Interp
from sogm_service.wire import limits
from sogm_service.wire.errors import ConfigError
from sogm_service.wire.keys import (
    DEFAULT_ISM_KEY,
    DEFAULT_MAP,
    DEFAULT_POSE_KEY,
    DEFAULT_PREFIX,
    MapKeys,
)
from sogm_service.wire.messages import GeodeticFix


class _Section(BaseModel):
    # Strict: ``resolution = "0.1"`` (a string) is refused, not read as a number; paths are
    # the one exception (TOML has no path type).
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, strict=True)


class MapSettings(_Section):
    name: Annotated[str, Field(pattern=limits.MAP_NAME_PATTERN)] = DEFAULT_MAP
    frame: str = "map"
    resolution: Annotated[float, Field(gt=0, le=100)] = 0.05
    tile_size: int = 256
    eps0: Annotated[float, Field(ge=logodds.MIN_EPS0, lt=0.5)] = logodds.DEFAULT_EPS0
    datum: GeodeticFix | None = None
    # Layers that forget: layer name or fnmatch pattern -> half-life (s, of the
    # ISM stamps); decay applied lazily per tile (sogm_service.core.map.forget).
    forget: dict[Annotated[str, Field(min_length=1, max_length=256)],
                 Annotated[float, Field(gt=0)]] = {}

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

    key_expr: str = DEFAULT_ISM_KEY
    interp: Interp = "biodds"
    matching: MatchingSettings = MatchingSettings()


class TileSettings(_Section):
    hysteresis_m: Annotated[float, Field(ge=0)] = 1.0
    roi_radius_tiles: Annotated[int, Field(ge=0, le=16)] = 1
    replicate_on_start: bool = False


class StorageSettings(_Section):
    directory: Annotated[Path, Field(strict=False)] | None = None
    checkpoint_interval_s: Annotated[float, Field(gt=0)] = 10.0
    memory_budget_mb: Annotated[float, Field(gt=0)] = 1024.0


class LimitSettings(_Section):
    max_ism_cells: Annotated[int, Field(gt=0)] = limits.MAX_ISM_CELLS
    max_ism_tiles: Annotated[int, Field(gt=0)] = limits.MAX_ISM_TILES
    max_payload_bytes: Annotated[int, Field(gt=0)] = limits.MAX_PAYLOAD_BYTES
    max_query_cells: Annotated[int, Field(gt=0)] = limits.MAX_QUERY_CELLS
    queue_size: Annotated[int, Field(ge=1, le=100000)] = limits.QUEUE_SIZE
    queue_policy: Literal["lossless", "latest"] = "lossless"
    fuse_workers: Annotated[int, Field(ge=1, le=64)] = limits.FUSE_WORKERS
    world_extent_m: Annotated[float, Field(gt=0, le=1e9)] = limits.WORLD_EXTENT_M
    max_layers: Annotated[int, Field(gt=0)] = limits.MAX_LAYERS
    max_robots: Annotated[int, Field(gt=0)] = limits.MAX_ROBOTS
    max_pending_poses: Annotated[int, Field(gt=0)] = limits.MAX_PENDING_POSES
    max_robot_name: Annotated[int, Field(gt=0)] = limits.MAX_ROBOT_NAME
    max_layer_name: Annotated[int, Field(gt=0, le=128)] = limits.MAX_LAYER_NAME
    max_query_read_cells: Annotated[int, Field(gt=0)] = limits.MAX_QUERY_READ_CELLS
    max_reply_bytes: Annotated[int, Field(gt=0)] = limits.MAX_REPLY_BYTES
    max_supercell_cells: Annotated[int, Field(gt=0)] = limits.MAX_SUPERCELL_CELLS
    max_heavy_queries: Annotated[int, Field(gt=0)] = limits.MAX_HEAVY_QUERIES
    busy_retry_s: Annotated[float, Field(gt=0)] = limits.BUSY_RETRY_S
    log_text_chars: Annotated[int, Field(ge=16)] = limits.LOG_TEXT_CHARS
    max_writer_queue_mb: Annotated[float, Field(gt=0)] = limits.MAX_WRITER_QUEUE_MB


class Ros2Settings(_Section):
    """ROS 2 over rmw_zenoh (:mod:`sogm_service.service.ros2.link`); needs the ``ros2`` extra."""

    enabled: bool = False
    domain: Annotated[int, Field(ge=0, le=232)] = 0  # ROS_DOMAIN_ID
    ism_prefix: str = "/ism"  # every nav_msgs/OccupancyGrid topic below it is an ISM
    ism_source: Annotated[int, Field(ge=0)] = 0  # ROS ISMs use [[ism]][i]'s interp/matching
    pose_topics: list[str] = ["/{robot}/pose"]  # geometry_msgs/PoseStamped
    odom_topics: list[str] = ["/{robot}/odom"]  # nav_msgs/Odometry (header frame = map)
    tf_topics: list[str] = ["/tf"]
    tf_static_topics: list[str] = ["/tf_static"]
    robot_frame: str = "{robot}/base_link"  # the TF chain [map] frame -> this
    humble: bool = False  # also accept Humble's TypeHashNotSupported
    topic_root: str = "/sogm"  # maps on /sogm/<map>/map and /sogm/<map>/layers/<layer>
    node_name: str = "sogm_service"
    publish_period_s: Annotated[float, Field(gt=0)] = 1.0
    region: Literal["robots", "known"] = "robots"
    region_radius_m: Annotated[float, Field(gt=0)] = 20.0
    max_publish_cells: Annotated[int, Field(gt=0)] = 2048 * 2048
    publish_layers: bool = True
    layers: list[str] | None = None  # layers published one by one (default all)
    fused_layers: list[str] | None = None  # layers pooled into /sogm/<map>/map (default all)
    fused_method: Literal["max", "bayes"] = "max"
    max_tilt_rad: Annotated[float, Field(gt=0)] = 0.01


class ClusterSettings(_Section):
    """One map over several servers (:mod:`sogm_service.service.cluster.cluster`)."""

    enabled: bool = False
    replicas: Annotated[int, Field(ge=1, le=16)] = 2  # owners per tile; 1: no replication
    fetch_timeout_s: Annotated[float, Field(gt=0, le=60)] = 1.0  # bound on a gather's wait
    fetch_cache_s: Annotated[float, Field(ge=0, le=60)] = 0.5  # fetched tiles reused this long
    fetch_cache_tiles: Annotated[int, Field(ge=0, le=100000)] = 64
    handover_timeout_s: Annotated[float, Field(gt=0, le=600)] = 10.0  # one tile's pull
    journal_limit: Annotated[int, Field(ge=1, le=1000000)] = 4096  # ISMs held per handover
    settle_s: Annotated[float, Field(ge=0, le=60)] = 0.2  # membership changes batched this long
    # A replica compares each tile that changed and then stayed quiet this long with its
    # primary's and adopts the primary's copy when they differ (0: never).
    reconcile_interval_s: Annotated[float, Field(ge=0, le=3600)] = 2.0


class ServiceConfig(_Section):
    map: MapSettings = MapSettings()
    ism: list[IsmSource] = [IsmSource()]
    pose_keys: list[str] = [DEFAULT_POSE_KEY]
    prefix: Annotated[str, Field(pattern=r"^[A-Za-z0-9_\-/]+$")] = DEFAULT_PREFIX
    tiles: TileSettings = TileSettings()
    storage: StorageSettings = StorageSettings()
    limits: LimitSettings = LimitSettings()
    zenoh: ZenohSettings = ZenohSettings()
    ros2: Ros2Settings = Ros2Settings()
    cluster: ClusterSettings = ClusterSettings()
    log_level: Literal["debug", "info", "warning", "error"] = "info"

    @field_validator("ism")
    @classmethod
    def _at_least_one(cls, v: list[IsmSource]) -> list[IsmSource]:
        if not v:
            raise ValueError("at least one ISM key expression is needed")
        return v

    @property
    def keys(self) -> MapKeys:
        """The key expressions of this map (``<prefix>/<map>/...``)."""
        return MapKeys(self.prefix, self.map.name)

    def key(self, *parts: str) -> str:
        """A key under ``<prefix>/<map>/``."""
        return self.keys.key(*parts)


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
