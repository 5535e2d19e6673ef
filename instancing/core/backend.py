"""The one place that chooses the Dr.Jit backend and finds a usable libLLVM.

Every other module imports its array types from here, so the same code runs
on ``drjit.cuda`` where a GPU exists (``INSTANCING_BACKEND=cuda``).

Dr.Jit's LLVM backend loads a system ``libLLVM`` at run time. Mitsuba 3.9's
kernels use the ``llvm.minimum``/``llvm.maximum`` intrinsics, which LLVM 15 and
16 cannot lower on x86 ("LLVM ERROR: Cannot select: fminimum", an abort with a
crash dump, measured here with Debian 12's libllvm15 and libllvm16). LLVM 19
(Debian 12's ``libllvm19``) works; 17 and 18 are untested and therefore
refused. We pick the newest suitable library ourselves, point Dr.Jit at it
through ``DRJIT_LIBLLVM_PATH`` before its first kernel, and turn every failure
into a :class:`~instancing.core.errors.BackendError` that says what to install.
"""

from __future__ import annotations

import glob
import os
import re

import numpy as np

from .errors import BackendError

#: Oldest LLVM major version verified to run Dr.Jit 1.5 and Mitsuba 3.9.1 here.
MIN_LLVM_MAJOR = 19

_LLVM_SEARCH_GLOBS = (
    "/usr/lib/x86_64-linux-gnu/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
    "/usr/lib/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/opt/homebrew/opt/llvm/lib/libLLVM*.dylib",
    "/usr/local/opt/llvm/lib/libLLVM*.dylib",
)

_INSTALL_HINT = (
    f"install LLVM {MIN_LLVM_MAJOR} or newer (Debian 12: `apt-get install -y libllvm19`, "
    "which `bash setup.sh` does for you), or set DRJIT_LIBLLVM_PATH to such a libLLVM"
)


def llvm_major_from_filename(path: str) -> int | None:
    """Read the LLVM major version from a library file name.

    Recognises ``libLLVM-19.so``, ``libLLVM-19.so.1``, ``libLLVM.so.19.1`` and
    ``/usr/lib/llvm-19/lib/libLLVM.so``; returns None when the name carries none.
    """
    name = os.path.basename(path)
    for pattern in (r"libLLVM-(\d+)", r"libLLVM\.so\.(\d+)", r"libLLVM\.(\d+)\.dylib"):
        match = re.match(pattern, name)
        if match:
            return int(match.group(1))
    match = re.search(r"/llvm-(\d+)/", path)
    return int(match.group(1)) if match else None


def find_libllvm() -> str | None:
    """Return the path of the newest libLLVM with major >= MIN_LLVM_MAJOR, or None."""
    candidates = []
    for pattern in _LLVM_SEARCH_GLOBS:
        for path in glob.glob(pattern):
            major = llvm_major_from_filename(path)
            if major is not None and major >= MIN_LLVM_MAJOR and os.path.isfile(path):
                candidates.append((major, path))
    return max(candidates)[1] if candidates else None


def _select_libllvm() -> None:
    """Point Dr.Jit at a suitable libLLVM before its LLVM backend starts."""
    chosen = os.environ.get("DRJIT_LIBLLVM_PATH")
    if chosen:
        if not os.path.isfile(chosen):
            raise BackendError(f"DRJIT_LIBLLVM_PATH={chosen!r} does not exist; {_INSTALL_HINT}.")
        major = llvm_major_from_filename(os.path.realpath(chosen)) or llvm_major_from_filename(chosen)
        if major is not None and major < MIN_LLVM_MAJOR:
            raise BackendError(
                f"DRJIT_LIBLLVM_PATH={chosen!r} is LLVM {major}, which aborts on Mitsuba 3.9's "
                f"kernels; {_INSTALL_HINT}.")
        return
    found = find_libllvm()
    if found is None:
        raise BackendError(f"no suitable libLLVM found for Dr.Jit's LLVM backend; {_INSTALL_HINT}.")
    os.environ["DRJIT_LIBLLVM_PATH"] = found


# Both settings are checked before any library loads. INSTANCING_THREADS=1 makes runs
# bit-reproducible on the LLVM backend: with several worker threads, sums that kernels
# accumulate with atomic adds (gradients in reverse mode) add their terms in whatever order
# the threads reach them, so two runs differ by a few ulps, which an optimisation can amplify.
BACKEND_NAME = os.environ.get("INSTANCING_BACKEND", "llvm").lower()
if BACKEND_NAME not in ("llvm", "cuda"):
    raise BackendError(f"INSTANCING_BACKEND={BACKEND_NAME!r} is not one of 'llvm', 'cuda'.")
_THREADS = os.environ.get("INSTANCING_THREADS")
if _THREADS is not None and (not _THREADS.isdigit() or int(_THREADS) < 1):
    raise BackendError(f"INSTANCING_THREADS={_THREADS!r} is not a positive integer.")
if BACKEND_NAME == "llvm":
    _select_libllvm()

import drjit as dr  # noqa: E402  (must follow the library selection above)

if BACKEND_NAME == "llvm":
    if not dr.has_backend(dr.JitBackend.LLVM):
        raise BackendError(
            f"Dr.Jit could not start its LLVM backend with "
            f"{os.environ.get('DRJIT_LIBLLVM_PATH')!r}; {_INSTALL_HINT}.")
    _version = dr.detail.llvm_version()
    if _version[0] < MIN_LLVM_MAJOR:
        raise BackendError(
            f"Dr.Jit runs on LLVM {'.'.join(map(str, _version))} (loaded from "
            f"{os.environ.get('DRJIT_LIBLLVM_PATH') or 'its default search'}), which aborts on "
            f"Mitsuba 3.9's kernels; {_INSTALL_HINT}. If Dr.Jit was used before importing "
            "instancing, import instancing first.")
    import drjit.llvm.ad as jit  # noqa: E402
    MITSUBA_VARIANT = "llvm_ad_rgb"
else:
    if not dr.has_backend(dr.JitBackend.CUDA):
        raise BackendError("INSTANCING_BACKEND=cuda but Dr.Jit found no CUDA device.")
    import drjit.cuda.ad as jit  # noqa: E402
    MITSUBA_VARIANT = "cuda_ad_rgb"
    # Dr.Jit's fast-math mode (its default) lowers rcp, division and square root on CUDA
    # to PTX approximations, rcp.approx.ftz.f64 included (a "gross approximation" in
    # PTX's words): the float64 re-intersection then lost its exactness. Measured on an
    # H200 with fast math: 99.9 % normal errors 4-5x Mitsuba's, hit points 29 ulp
    # (target 4) at ordinary scales, flipped normals on the degenerate axis. The LLVM
    # backend is IEEE either way. The flag is per thread: this sets it in the importing one.
    dr.set_flag(dr.JitFlag.FastMath, False)

if _THREADS is not None:
    dr.set_thread_count(int(_THREADS))

Float = jit.Float
Float64 = jit.Float64
UInt32 = jit.UInt32
Int32 = jit.Int32
Bool = jit.Bool
Array2f = jit.Array2f
Array2f64 = jit.Array2f64
Array3f = jit.Array3f
Array3f64 = jit.Array3f64
Array4f = jit.Array4f
Array4f64 = jit.Array4f64
Array3i = jit.Array3i
Array3u = jit.Array3u
Array3b = jit.Array3b
Matrix3f = jit.Matrix3f
Matrix3f64 = jit.Matrix3f64
Matrix4f = jit.Matrix4f
Matrix4f64 = jit.Matrix4f64
TensorXf = jit.TensorXf
Array2u = jit.Array2u


def mitsuba_module():
    """Mitsuba, set to the variant of our backend (``MITSUBA_VARIANT``: its arrays are ours,
    so its BSDF building blocks run on our arrays and its scenes take our meshes). Imported
    on first use; a different variant set before is replaced."""
    import mitsuba as mi
    if mi.variant() != MITSUBA_VARIANT:
        mi.set_variant(MITSUBA_VARIANT)
    return mi


def device_array(array_type, values):
    """A flat array (``Float``, ``Float64``, ``UInt32``) holding the 1D NumPy ``values``, in storage
    that Dr.Jit allocated itself (64-byte aligned). The scene's arrays made from NumPy
    data go through here, for two reasons:

    - Dr.Jit's LLVM backend turns a gather of 2, 4 or 8 consecutive entries
      (``dr.gather(Array4f, ...)``, every component used) into packet loads, one vector
      load per lane and a transpose, only from a 64-byte aligned buffer. An array made
      from NumPy data wraps the NumPy buffer without copying it (16-byte aligned for
      large arrays here; ``dr.copy`` of it, or a kernel's result computed from it,
      measured 16-byte aligned as well), and each such gather then becomes one scalar
      gather per component; ``dr.empty`` storage measured 64-byte aligned every time.
      Measured on this machine, per SIMD packet of 16 lanes: a scalar gather ~35
      cycles, a float4 packet load ~52 (for four components).
    - A kernel loads an array of one entry as a scalar, with the alignment of its
      address written into the code ("align 1" or "align 4" for small NumPy buffers):
      a scene with one emitter compiled its render kernel anew after every
      ``set_transforms`` (cornell_box, showcase: 0.5 - 2.4 s per frame). One entry
      becomes an opaque scalar here (always "align 4").
    """
    return device_arrays(array_type, values)[0]


def device_arrays(array_type, *values) -> list:
    """:func:`device_array` of each of several 1D NumPy arrays of one dtype.

    One-entry values become opaque scalars (~2 us each, no kernel). The others are
    copied into one NumPy buffer that starts on a 64-byte boundary, and one kernel
    per width (the same for every layout of the parts) scatters them into Dr.Jit
    storage: a kernel reading NumPy buffers is compiled for their alignment, so
    separate buffers compiled a new kernel on most calls (12 - 17 ms each for an
    optimisation step's 16 matrix entries).
    """
    out = [None] * len(values)
    parts = [(k, np.ravel(v)) for k, v in enumerate(values)]
    for k, v in parts:
        if len(v) == 1:
            out[k] = dr.opaque(array_type, v[0].item())
        elif len(v) == 0:
            out[k] = dr.zeros(array_type, 0)
    parts = [(k, v) for k, v in parts if len(v) > 1]
    if parts:
        total = sum(len(v) for _, v in parts)
        dtype = np.dtype({dr.VarType.Float32: np.float32, dr.VarType.Float64: np.float64}.get(
            dr.type_v(array_type), np.uint32))
        storage = np.empty(total + 64 // dtype.itemsize, dtype)
        start = (-storage.ctypes.data % 64) // dtype.itemsize
        flat = storage[start:start + total]
        offset = 0
        for _, v in parts:
            flat[offset:offset + len(v)] = v
            offset += len(v)
        source = array_type(flat)
        offset = 0
        for k, v in parts:
            index = dr.arange(jit.UInt32, len(v))
            out[k] = dr.empty(array_type, len(v))
            # (An opaque offset: as a literal it would make a kernel of its own per layout.)
            dr.scatter(out[k], dr.gather(array_type, source, index + dr.opaque(jit.UInt32, offset)), index)
            offset += len(v)
    dr.eval(*out)
    return out


def device_vectors(values) -> "Array3f":
    """An ``Array3f`` of the (N, 3) NumPy ``values``, each component a :func:`device_array`."""
    values = np.asarray(values, np.float32)
    return Array3f(*device_arrays(Float, *values.T))


def vectors_from_rows(rows) -> "Array3f":
    """An ``Array3f`` of the (N, 3) NumPy ``rows`` as float32, one contiguous column each."""
    rows = np.asarray(rows, np.float32)
    return Array3f(*[np.ascontiguousarray(rows[:, k]) for k in range(3)])


def rows_from_vectors(vectors, dtype=np.float32) -> np.ndarray:
    """The (N, 3) NumPy rows of an ``Array3f`` (or of Mitsuba's vectors), as ``dtype``,
    converted one column at a time (faster than the nested array whole, transposed)."""
    return np.stack([host_array(vectors[k], dtype) for k in range(3)], axis=1)


def host_array(values, dtype=None) -> np.ndarray:
    """A flat Dr.Jit array as a NumPy array (of ``dtype`` where given): its own ``numpy()``,
    which costs less than half of ``np.asarray``'s protocol (about 1 against 2.5 us)."""
    out = values.numpy()
    return out if dtype is None else out.astype(dtype, copy=False)


__all__ = [
    "dr", "jit", "BACKEND_NAME", "MITSUBA_VARIANT", "MIN_LLVM_MAJOR", "find_libllvm", "mitsuba_module",
    "Float", "Float64", "UInt32", "Int32", "Bool", "Array2u", "Array3f", "Array3f64", "Array4f",
    "Array4f64", "Array3i", "Array3u", "Array3b", "Matrix3f", "Matrix3f64", "Matrix4f", "Matrix4f64",
    "TensorXf",
    "device_array", "device_arrays", "device_vectors", "vectors_from_rows", "rows_from_vectors", "host_array",
]
