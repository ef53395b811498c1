"""The map server: the wiring (``server``) and its parts (ingestion, admission, fusion, queries,
acks, checkpoints, fleet tracking, stats).
"""
