"""The machine a benchmark ran on, recorded beside its figures.

Figures from different machines do not compare (the suite's runs have met Intel and AMD
processors, with AVX-512 and without): every results file that the performance page reads
records the machine of each of its parts, and the page lists them.
"""

from __future__ import annotations

import os
import platform
from importlib import metadata
from pathlib import Path

#: The widest SIMD extension of the processor that Dr.Jit's LLVM backend uses, by the flag
#: that Linux lists for it (first match).
SIMD_FLAGS = (("avx512f", "AVX-512"), ("avx2", "AVX2"), ("avx", "AVX"), ("sse4_2", "SSE4.2"),
              ("asimd", "NEON"))


def describe() -> dict:
    """The processor's model, its logical cores, Dr.Jit's threads, the SIMD extension and the
    versions of Python, Dr.Jit and Mitsuba."""
    from instancing.core.backend import dr  # (the page that prints these lines needs no backend)
    model, flags = None, set()
    cpuinfo = Path("/proc/cpuinfo")
    # (The first processor's entries; Linux lists x86 flags as "flags", Arm's as "Features".)
    for entry in cpuinfo.read_text().splitlines() if cpuinfo.is_file() else ():
        key, _, value = (part.strip() for part in entry.partition(":"))
        if key == "model name" and model is None:
            model = value
        elif key in ("flags", "Features") and not flags:
            flags = set(value.split())
    model = model or platform.processor() or platform.machine()
    simd = next((name for flag, name in SIMD_FLAGS if flag in flags), "unknown")
    return {"cpu": model, "cores": os.cpu_count(), "threads": dr.thread_count(), "simd": simd,
            "python": platform.python_version(), "drjit": metadata.version("drjit"),
            "mitsuba": metadata.version("mitsuba")}


def line(machine: dict) -> str:
    """One line for a machine of :func:`describe`."""
    return (f"{machine['cpu']}, {machine['cores']} logical cores ({machine['threads']} Dr.Jit "
            f"threads), {machine['simd']}; Python {machine['python']}, Dr.Jit {machine['drjit']}, "
            f"Mitsuba {machine['mitsuba']}")
