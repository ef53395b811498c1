"""Several servers, one map: membership and tile ownership, handover, replication and gathered
queries.
"""
