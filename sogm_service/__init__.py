"""sogm-service: semantical occupancy grid maps (SOGMs) for robot fleets, served over Zenoh."""

__version__ = "0.1.0"
