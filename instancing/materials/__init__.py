"""Materials: Mitsuba's BSDFs as flat per-material parameter tables and their kernels."""
