"""The public Python client: ``from sogm_service.client import MapClient``.

The client lives in :mod:`sogm_service.client.mapclient`, its results in
:mod:`sogm_service.client.results` and its ISM helpers in :mod:`sogm_service.client.isms`; this
module keeps the documented import path stable and gathers what a client program needs in one
place.
"""

from sogm_service.client.mapclient import MapClient
from sogm_service.client.results import GridResult
from sogm_service.core.geometry import GridGeometry, Pose2D
from sogm_service.wire.errors import (
    ClientError,
    ConnectError,
    InvalidIsmError,
    IsmNotFusedError,
    QueryTimeoutError,
    ServiceError,
)

__all__ = ["ClientError", "ConnectError", "GridGeometry", "GridResult", "InvalidIsmError",
           "IsmNotFusedError", "MapClient", "Pose2D", "QueryTimeoutError", "ServiceError"]
