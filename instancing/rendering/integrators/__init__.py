"""Integrators: functions from world rays to radiance or AOV channels."""
