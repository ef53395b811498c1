"""Scan matching (paper section III-C.2): ORB features, RANSAC and ECC, and the alignment step that
applies a correction.
"""
