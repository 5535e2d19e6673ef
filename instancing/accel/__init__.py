"""Acceleration structures over instances (grid, BVH) and over mesh triangles (BVH)."""
