"""Readers for the files a scene refers to (triangle meshes)."""
