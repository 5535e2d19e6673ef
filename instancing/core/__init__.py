"""Foundation: the Dr.Jit backend, errors, transforms, sample warps, random streams,
rounding-error bounds, ray offsets and box tests. Imports nothing above it."""
