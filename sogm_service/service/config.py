"""Service configuration: a TOML file validated by pydantic; every field has a sane default.

``sogm-service serve`` with no file serves map ``default`` at 5 cm in frame ``map``, listens for
ISMs on ``ism/**`` and poses on ``pose/**``, keeps tiles in memory only, and runs Zenoh as a peer
with multicast scouting off.  Every field carries its description and unit
(:func:`pydantic.Field`); :mod:`sogm_service.service.config_reference` renders them as the
configuration reference and as ``deploy/sogm-service.toml``.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    JsonValue,
    ValidationError,
    field_validator,
    model_validator,
)

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


def _doc(description: str, unit: str = "", example: JsonValue = None,
         **constraints: Any) -> Any:
    """A field's description, its unit and, for a field that is unset by default, an example
    value: what the configuration reference and ``deploy/sogm-service.toml`` show."""
    extra: dict[str, JsonValue] = {"unit": unit}
    if example is not None:
        extra["example"] = example
    return Field(description=description, json_schema_extra=extra, **constraints)


def _limit(path: str, **constraints: Any) -> Any:
    """A limit's field: description, unit, refusal code and counters from
    :data:`sogm_service.wire.limits.LIMITS` (its default is the constant there too)."""
    lim = limits.LIMITS[path]
    return Field(description=lim.bounds, json_schema_extra={
        "unit": lim.unit, "refused_as": lim.refused_as, "counters": list(lim.counters)},
        **constraints)


class _Section(BaseModel):
    # Strict: ``resolution = "0.1"`` (a string) is refused, not read as a number; paths are
    # the one exception (TOML has no path type).
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, strict=True)


class MapSettings(_Section):
    """The map this server serves."""

    name: Annotated[str, _doc("The map's name: part of every key and of every tile file "
                              "name.", pattern=limits.MAP_NAME_PATTERN)] = DEFAULT_MAP
    frame: Annotated[str, _doc("The map frame; ISMs in any other frame are refused "
                               "(wrong_frame).")] = "map"
    resolution: Annotated[float, _doc("Edge of a cell of the stored map (m).", "m",
                                      gt=0, le=100)] = 0.05
    tile_size: Annotated[int, _doc("Cells per tile edge: a power of two from 16 to 4096.",
                                   "cells")] = 256
    eps0: Annotated[float, _doc(
        "Probability clamp: every cell stays in [eps0, 1 - eps0]; also the eps0 of the biodds "
        "resampling.", "", ge=logodds.MIN_EPS0, lt=0.5)] = logodds.DEFAULT_EPS0
    datum: Annotated[GeodeticFix | None, _doc(
        "A geodetic datum (latitude, longitude in degrees, altitude in m) of the map origin, "
        "the map frame ENU-aligned at it: tile-switch events then carry each tile origin's "
        "latitude, longitude and altitude. Unset: a local-only map.", "",
        {"latitude": 52.0302, "longitude": 8.5325, "altitude": 110.0})] = None
    # Decay is applied lazily per tile (sogm_service.core.map.forget).
    forget: Annotated[dict[Annotated[str, Field(min_length=1, max_length=256)],
                           Annotated[float, Field(gt=0)]], _doc(
        "Layers that forget (decay toward unknown): layer name or fnmatch pattern -> "
        "half-life in seconds of the ISM stamps, e.g. { \"*/people\" = 30.0 }.", "s")] = {}

    @field_validator("tile_size")
    @classmethod
    def _power_of_two(cls, v: int) -> int:
        if v < 16 or v > 4096 or v & (v - 1):
            raise ValueError("tile_size must be a power of two between 16 and 4096")
        return v


class MatchingSettings(_Section):
    """ORB scan matching of this source's ISMs against the map (paper section III-C.2)."""

    mode: Annotated[Literal["off", "correct", "report"], _doc(
        "off: no matching; correct: an accepted match moves the ISM to the corrected pose "
        "before it is fused; report: the ISM is fused as claimed and the correction only "
        "published.")
    ] = "off"
    on_failure: Annotated[Literal["fuse", "reject"], _doc(
        "What happens to an ISM whose match is not accepted in correct mode: fused as "
        "claimed, or rejected.")] = "fuse"
    layer: Annotated[str | None, _doc(
        "The map layer to match against; unset: the ISM's own layer.", "",
        "obstacle")] = None
    model: Annotated[Literal["similarity", "homography"], _doc(
        "The transform fitted: similarity (rigid plus scale) or homography (the paper's).")
    ] = "similarity"
    # 6: measured on the Intel log (``sogm-service eval matching``): 65 % of perturbed scans
    # accepted, 0.05 % of those grossly wrong; 12 accepts 31 %.
    min_inliers: Annotated[int, _doc(
        "Fewest ORB matches consistent with the fitted transform for a match to be accepted "
        "(6 on the Intel log: 65 % of perturbed scans accepted, 0.05 % of those grossly "
        "wrong).", "matches", ge=4)] = 6
    max_translation_m: Annotated[float, _doc(
        "Largest translation a match may correct (m).", "m", gt=0)] = 1.0
    max_rotation_deg: Annotated[float, _doc(
        "Largest rotation a match may correct (degrees).", "deg", gt=0, le=180)] = 15.0
    # Measured: 1 m more changes nothing on the Intel log, so none by default.
    margin_m: Annotated[float, _doc(
        "Map matched against beyond the reach of the largest accepted correction (m).", "m",
        ge=0)] = 0.0


class IsmSource(_Section):
    """One ISM key expression and how its ISMs are treated (several tables allowed). The layer
    of an ISM is its ``layer`` field, else the key's remainder after the literal prefix:
    ``ism/robot1/laser/obstacle`` -> ``robot1/laser/obstacle``."""

    key_expr: Annotated[str, _doc("The Zenoh key expression ISMs arrive on.")] = DEFAULT_ISM_KEY
    interp: Annotated[Interp, _doc("Resampling of an ISM into the map: biodds, bilinear or "
                                   "nearest.")] = "biodds"
    matching: MatchingSettings = MatchingSettings()


class TileSettings(_Section):
    """Which tiles are kept loaded: those around each robot."""

    hysteresis_m: Annotated[float, _doc(
        "A robot switches tile only this far past the tile edge (m).", "m", ge=0)] = 1.0
    roi_radius_tiles: Annotated[int, _doc(
        "Tiles kept loaded around each robot's tile (1: 3 x 3).", "tiles", ge=0, le=16)] = 1
    replicate_on_start: Annotated[bool, _doc(
        "Copy the map of a live server of this map (tiles/**) before serving.")] = False


class StorageSettings(_Section):
    """Where tiles are kept, and how much of them in memory."""

    directory: Annotated[Path | None, _doc(
        "The tile store's directory; unset: an in-memory map.", "",
        "/var/lib/sogm-service", strict=False)] = None
    checkpoint_interval_s: Annotated[float, _doc(
        "Dirty tiles are written this often (s): what a crash may lose.", "s", gt=0)] = 10.0
    memory_budget_mb: Annotated[float, _limit("storage.memory_budget_mb", gt=0)
                                ] = limits.MEMORY_BUDGET_MB


class StoreSettings(_Section):
    """Tiles on an object store instead of a directory: several servers of one map (a
    cluster) may share one bucket.  Region and credentials come from the usual AWS
    environment variables and config files (boto3)."""

    url: Annotated[str | None, _doc(
        "The tile store on an object store, s3://bucket/prefix (instead of "
        "storage.directory); unset: the directory store, if any.", "",
        "s3://sogm-tiles/site-a", pattern=r"^s3://[a-z0-9][a-z0-9.\-]{1,61}[a-z0-9](/.*)?$")
    ] = None
    endpoint_url: Annotated[str | None, _doc(
        "The S3 endpoint (a SeaweedFS or MinIO server, a regional endpoint); unset: the "
        "cloud's default for the region.", "", "http://127.0.0.1:8333",
        pattern=r"^https?://")] = None


class LimitSettings(_Section):
    """What one message, query or client may cost; each input is priced from its header before
    any work and refused with a code when it is over a limit."""

    max_ism_cells: Annotated[int, _limit("limits.max_ism_cells", gt=0)] = limits.MAX_ISM_CELLS
    max_ism_tiles: Annotated[int, _limit("limits.max_ism_tiles", gt=0)] = limits.MAX_ISM_TILES
    max_payload_bytes: Annotated[int, _limit("limits.max_payload_bytes", gt=0)
                                 ] = limits.MAX_PAYLOAD_BYTES
    max_query_cells: Annotated[int, _limit("limits.max_query_cells", gt=0)
                               ] = limits.MAX_QUERY_CELLS
    queue_size: Annotated[int, _limit("limits.queue_size", ge=1, le=100000)] = limits.QUEUE_SIZE
    queue_policy: Annotated[Literal["lossless", "latest"], _doc(
        "When the ISM queue is full: lossless pushes back through Zenoh to the publishers "
        "(which use congestion control BLOCK); latest keeps only the newest ISM per key "
        "waiting and counts the dropped ones (isms_dropped_latest).")] = "lossless"
    fuse_workers: Annotated[int, _doc(
        "Threads fusing ISMs, each owning whole rows of tiles; the map is the same for any "
        "number. 1 is fastest on a 2-core machine; raise it with cores to spare and measure "
        "with sogm-service bench ingest.", "threads", ge=1, le=64)] = limits.FUSE_WORKERS
    rx_threads: Annotated[int, _doc(
        "Zenoh receive threads of the server process. With queue_policy lossless a full ISM "
        "queue pushes back by holding the receive thread of each publisher's link; queries "
        "are received by the others, so keep it above the number of links that may push "
        "back at once (an environment ZENOH_RUNTIME wins).", "threads", ge=2, le=256)] = 16
    world_extent_m: Annotated[float, _limit("limits.world_extent_m", gt=0, le=1e9)
                              ] = limits.WORLD_EXTENT_M
    max_layers: Annotated[int, _limit("limits.max_layers", gt=0)] = limits.MAX_LAYERS
    max_robots: Annotated[int, _limit("limits.max_robots", gt=0)] = limits.MAX_ROBOTS
    max_pending_poses: Annotated[int, _limit("limits.max_pending_poses", gt=0)
                                 ] = limits.MAX_PENDING_POSES
    max_robot_name: Annotated[int, _limit("limits.max_robot_name", gt=0)
                              ] = limits.MAX_ROBOT_NAME
    max_layer_name: Annotated[int, _limit("limits.max_layer_name", gt=0, le=128)
                              ] = limits.MAX_LAYER_NAME
    max_query_read_cells: Annotated[int, _limit("limits.max_query_read_cells", gt=0)
                                    ] = limits.MAX_QUERY_READ_CELLS
    max_reply_bytes: Annotated[int, _limit("limits.max_reply_bytes", gt=0)
                               ] = limits.MAX_REPLY_BYTES
    max_supercell_cells: Annotated[int, _limit("limits.max_supercell_cells", gt=0)
                                   ] = limits.MAX_SUPERCELL_CELLS
    max_heavy_queries: Annotated[int, _limit("limits.max_heavy_queries", gt=0)
                                 ] = limits.MAX_HEAVY_QUERIES
    max_region_tiles: Annotated[int, _limit("limits.max_region_tiles", gt=0)
                                ] = limits.MAX_REGION_TILES
    busy_retry_s: Annotated[float, _limit("limits.busy_retry_s", gt=0)] = limits.BUSY_RETRY_S
    log_text_chars: Annotated[int, _limit("limits.log_text_chars", ge=16)
                              ] = limits.LOG_TEXT_CHARS
    max_writer_queue_mb: Annotated[float, _limit("limits.max_writer_queue_mb", gt=0)
                                   ] = limits.MAX_WRITER_QUEUE_MB


class Ros2Settings(_Section):
    """ROS 2 over rmw_zenoh (:mod:`sogm_service.service.ros2.link`); needs the ``ros2`` extra
    (``pip install 'sogm-service[ros2]'``)."""

    enabled: Annotated[bool, _doc("Serve ROS 2 topics beside the native keys.")] = False
    domain: Annotated[int, _doc("The ROS_DOMAIN_ID.", "", ge=0, le=232)] = 0
    ism_prefix: Annotated[str, _doc(
        "Every nav_msgs/OccupancyGrid topic below it is an ISM.")] = "/ism"
    ism_source: Annotated[int, _doc(
        "Index of the [[ism]] table whose interp and matching ROS ISMs use.", "",
        ge=0)] = 0
    pose_topics: Annotated[list[str], _doc(
        "geometry_msgs/PoseStamped topics (frame: the map frame).")] = ["/{robot}/pose"]
    odom_topics: Annotated[list[str], _doc(
        "nav_msgs/Odometry topics (header frame: the map frame).")] = ["/{robot}/odom"]
    tf_topics: Annotated[list[str], _doc("TF topics.")] = ["/tf"]
    tf_static_topics: Annotated[list[str], _doc("Static TF topics.")] = ["/tf_static"]
    robot_frame: Annotated[str, _doc(
        "A robot's pose is the TF chain from the map frame to this frame.")
    ] = "{robot}/base_link"
    humble: Annotated[bool, _doc(
        "Also accept the samples of Humble (TypeHashNotSupported).")] = False
    topic_root: Annotated[str, _doc(
        "Maps are published on <topic_root>/<map>/map and <topic_root>/<map>/layers/<layer>.")
    ] = "/sogm"
    node_name: Annotated[str, _doc("The ROS node name.")] = "sogm_service"
    publish_period_s: Annotated[float, _doc(
        "Maps are republished this often, when they changed (s).", "s", gt=0)] = 1.0
    full_period_s: Annotated[float, _doc(
        "Between whole OccupancyGrids only the changed rectangles go out (on "
        "<topic>_updates); a whole grid goes out again when the extent grows, when a ROS "
        "subscriber of the topic appears, and after updates at most this long after the last "
        "one (s; 0: not by time).", "s", ge=0)] = 300.0
    region: Annotated[Literal["recent", "robots", "known"], _doc(
        "The published region: what is known around the ISMs fused lately (with or without "
        "robot poses), around the robots' poses, or the whole known map.")] = "recent"
    region_radius_m: Annotated[float, _doc(
        "With region robots: the radius published around each robot (m).", "m", gt=0)] = 20.0
    max_publish_cells: Annotated[int, _doc(
        "The published window is shrunk to at most this many cells.", "cells",
        gt=0)] = 2048 * 2048
    publish_layers: Annotated[bool, _doc(
        "Also publish each layer on <topic_root>/<map>/layers/<layer>.")] = True
    layers: Annotated[list[str] | None, _doc(
        "Layers published one by one, by name or class pattern (a pattern's matching layers "
        "fused by the Bayesian rule into one grid, on a topic spelling * as all); unset: every "
        "layer.", "", ["*/laser/obstacle"])] = None
    fused_layers: Annotated[list[str] | None, _doc(
        "Layers or class patterns pooled into <topic_root>/<map>/map; unset: every layer.", "",
        ["*/laser/obstacle", "*/person"])] = None
    fused_method: Annotated[Literal["max", "bayes"], _doc(
        "How the layers are pooled (paper Eq. 6): max (P_M) or bayes (P_B).")] = "max"
    max_tilt_rad: Annotated[float, _doc(
        "A grid origin tilted more than this (rad) is refused (non_planar).", "rad",
        gt=0)] = 0.01


class Nav2Settings(_Section):
    """nav2 costmap filter masks derived live from the semantic layers, published with --ros2
    over the map's region and period (:mod:`sogm_service.adapters.ros2.filters`)."""

    keepout: Annotated[list[Annotated[str, Field(min_length=1, max_length=256)]], _doc(
        "Layers or class patterns kept out of: <topic_root>/<map>/keepout_mask is 100 where "
        "one is at or above keepout_threshold; empty: no keepout mask.", "",
        ["*/person"])] = []
    keepout_threshold: Annotated[float, _doc(
        "Probability at or above which a cell is kept out.", "", gt=0.5, lt=1)] = 0.6
    speed: Annotated[dict[Annotated[str, Field(min_length=1, max_length=256)],
                          Annotated[int, Field(ge=1, le=100)]], _doc(
        "Layers or class patterns -> speed limit in percent of the maximum speed (1..100) on "
        "<topic_root>/<map>/speed_mask; where several apply the lowest wins; empty: no speed "
        "mask.", "%", {"*/pallet": 40})] = {}
    speed_threshold: Annotated[float, _doc(
        "Probability at or above which a speed class limits a cell.", "", gt=0.5, lt=1)] = 0.6
    whole_masks: Annotated[bool, _doc(
        "Send a mask whole at every change. nav2's KeepoutFilter and SpeedFilter read whole "
        "grids from the mask topic only (not <topic>_updates); false: the changed rectangles "
        "on <mask topic>_updates as for the map, which nav2's filters see only at the next "
        "whole grid ([ros2] full_period_s).")] = True


class ClusterSettings(_Section):
    """One map over several servers (:mod:`sogm_service.service.cluster.cluster`)."""

    enabled: Annotated[bool, _doc(
        "Join the cluster of this map; members see each other by their liveliness tokens.")
    ] = False
    replicas: Annotated[int, _doc(
        "Owners per tile (rendezvous hashing); 1 turns replication off.", "servers",
        ge=1, le=16)] = 2
    fetch_timeout_s: Annotated[float, _doc(
        "A query waits at most this long for a tile it must fetch from its owner (s; then "
        "no_owner).", "s", gt=0, le=60)] = 1.0
    fetch_cache_s: Annotated[float, _doc(
        "A fetched tile is reused this long (s): reads may be this stale.", "s",
        ge=0, le=60)] = 0.5
    fetch_cache_tiles: Annotated[int, _doc(
        "At most this many fetched tiles are kept.", "tiles", ge=0, le=100000)] = 64
    handover_timeout_s: Annotated[float, _doc(
        "Bound on one tile's pull from its owners during a membership change (s).", "s",
        gt=0, le=600)] = 10.0
    journal_limit: Annotated[int, _doc(
        "ISMs kept for the tiles being handed over (then the oldest go).", "ISMs",
        ge=1, le=1000000)] = 4096
    settle_s: Annotated[float, _doc(
        "Membership changes arriving this close together are handled together (s).", "s",
        ge=0, le=60)] = 0.2
    reconcile_interval_s: Annotated[float, _doc(
        "A replica compares each tile that changed and then stayed quiet this long with its "
        "primary's and adopts the primary's copy when they differ (s; 0: never).", "s",
        ge=0, le=3600)] = 2.0


class ServiceConfig(_Section):
    """The whole configuration file; its top-level fields come before any table."""

    map: MapSettings = MapSettings()
    ism: list[IsmSource] = [IsmSource()]
    pose_keys: Annotated[list[str], _doc(
        "Key expressions of the robots' poses (the tile manager follows them).")
    ] = [DEFAULT_POSE_KEY]
    prefix: Annotated[str, _doc(
        "The server's own keys live under <prefix>/<map>/.",
        pattern=r"^[A-Za-z0-9_\-/]+$")] = DEFAULT_PREFIX
    tiles: TileSettings = TileSettings()
    storage: StorageSettings = StorageSettings()
    store: StoreSettings = StoreSettings()
    limits: LimitSettings = LimitSettings()
    zenoh: ZenohSettings = ZenohSettings()
    ros2: Ros2Settings = Ros2Settings()
    nav2: Nav2Settings = Nav2Settings()
    cluster: ClusterSettings = ClusterSettings()
    log_level: Annotated[Literal["debug", "info", "warning", "error"], _doc(
        "The log level.")] = "info"

    @model_validator(mode="after")
    def _one_store(self) -> ServiceConfig:
        if self.store.url is not None and self.storage.directory is not None:
            raise ValueError("store.url and storage.directory name two tile stores: set one")
        return self

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
