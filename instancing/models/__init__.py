"""Base models in object space: analytic shapes and triangle meshes."""
