"""Verification: the float64 reference, the Mitsuba cross-check, the numerical stress
suite, gradient checks and the measures they share."""
