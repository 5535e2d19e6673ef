"""Differentiation: scene parameters (``traverse``), recorded optimisation steps and
recovery of instance transforms from images."""
