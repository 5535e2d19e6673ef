"""Rendering: ``render()`` and the film, the boundary derivative term, recorded renders
and the integrators."""
