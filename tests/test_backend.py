"""Tests of the backend choice and the libLLVM search in :mod:`instancing.core.backend`.

Importing with an unusable libLLVM must fail with a clear ``BackendError`` that says what to
install, never with LLVM's own abort ("LLVM ERROR: Cannot select", a stack dump). Those
imports run in subprocesses, because the backend is chosen once per process.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

import instancing.core.backend as backend
from instancing.core.backend import BACKEND_NAME, MIN_LLVM_MAJOR, find_libllvm, llvm_major_from_filename

REPO = Path(__file__).resolve().parent.parent
SYSTEM_LIBS = Path("/usr/lib/x86_64-linux-gnu")


@pytest.mark.parametrize("name, major", [
    ("libLLVM-19.so.1", 19),
    ("libLLVM.so.19.1", 19),
    ("/usr/lib/llvm-17/lib/libLLVM.so", 17),
    ("libLLVM-15.so", 15),
    ("/usr/lib/x86_64-linux-gnu/libLLVM-14.0.6.so.1", 14),
    ("/usr/lib/x86_64-linux-gnu/libLLVM.so.20.1", 20),
    ("/opt/homebrew/opt/llvm/lib/libLLVM.21.dylib", 21),
    ("/usr/lib/llvm-18/lib/libLLVM-19.so", 19),  # the file name wins over the folder
    ("libLLVM.so", None),
    ("/usr/lib/libLLVM.dylib", None),
    ("/usr/lib64/libLLVM-.so", None),
])
def test_llvm_major_from_filename(name, major):
    assert llvm_major_from_filename(name) == major


def _pythonpath() -> str:
    """The repository first, then the caller's own path (packages installed there)."""
    return os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])])


def _import_instancing(env_changes: dict[str, str]) -> subprocess.CompletedProcess:
    """``import instancing`` in a fresh interpreter with the given environment changes."""
    env = dict(os.environ)
    env.pop("DRJIT_LIBLLVM_PATH", None)
    env["INSTANCING_BACKEND"] = "llvm"
    env["PYTHONPATH"] = _pythonpath()
    env.update(env_changes)
    # A real scene query after the import: a library that slipped through would abort here.
    code = ("import instancing, numpy as np\n"
            "s = instancing.load_scene({'instances': [{'model': 'sphere'}]})\n"
            "print(s.intersect(np.array([[0, 0, -5.0]]), np.array([[0, 0, 1.0]])).t)\n")
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                          timeout=120, cwd=str(REPO))


def _assert_clean_backend_error(proc: subprocess.CompletedProcess) -> None:
    assert proc.returncode != 0, proc.stdout
    assert "BackendError" in proc.stderr, proc.stderr
    assert "libllvm19" in proc.stderr, proc.stderr
    assert "LLVM ERROR" not in proc.stderr, proc.stderr
    assert "Stack dump" not in proc.stderr, proc.stderr


@pytest.mark.skipif(BACKEND_NAME == "cuda" and find_libllvm() is None,
                    reason="suite runs on CUDA on a machine without libLLVM")
def test_default_import_works():
    # Positive control for the subprocess checks below: the same script succeeds (t = 4).
    proc = _import_instancing({})
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[4.]"


def test_nonexistent_libllvm_path_fails_cleanly(tmp_path):
    missing = tmp_path / "libLLVM-19.so.1"
    proc = _import_instancing({"DRJIT_LIBLLVM_PATH": str(missing)})
    _assert_clean_backend_error(proc)
    assert str(missing) in proc.stderr


OLD_LLVMS = [SYSTEM_LIBS / name for name in ("libLLVM-15.so.1", "libLLVM-16.so.1", "libLLVM-14.so.1")]


@pytest.mark.parametrize("lib", OLD_LLVMS, ids=lambda p: p.name)
def test_old_libllvm_fails_cleanly(lib):
    if not lib.exists():
        pytest.skip(f"{lib} is not installed")
    proc = _import_instancing({"DRJIT_LIBLLVM_PATH": str(lib)})
    _assert_clean_backend_error(proc)
    assert "LLVM 1" in proc.stderr  # names the version it refused


def test_old_libllvm_behind_unversioned_symlink_fails_cleanly(tmp_path):
    lib = SYSTEM_LIBS / "libLLVM-15.so.1"
    if not lib.exists():
        pytest.skip(f"{lib} is not installed")
    link = tmp_path / "libLLVM.so"
    link.symlink_to(lib)
    _assert_clean_backend_error(_import_instancing({"DRJIT_LIBLLVM_PATH": str(link)}))


def test_old_libllvm_with_unversioned_name_fails_cleanly(tmp_path):
    # A hard link hides the version from the file name entirely, so only the check of the
    # version Dr.Jit actually loaded can catch it.
    lib = SYSTEM_LIBS / "libLLVM-15.so.1"
    if not lib.exists():
        pytest.skip(f"{lib} is not installed")
    link = tmp_path / "libLLVM.so"
    try:
        os.link(os.path.realpath(lib), link)
    except OSError as err:
        pytest.skip(f"cannot hard-link {lib} here: {err}")
    _assert_clean_backend_error(_import_instancing({"DRJIT_LIBLLVM_PATH": str(link)}))


def test_unknown_backend_name_fails_cleanly():
    proc = _import_instancing({"INSTANCING_BACKEND": "vulkan"})
    assert proc.returncode != 0
    assert "BackendError" in proc.stderr and "vulkan" in proc.stderr, proc.stderr


@pytest.mark.parametrize("value", ["0", "two", "-1"])
def test_bad_thread_count_fails_cleanly(value):
    proc = _import_instancing({"INSTANCING_THREADS": value})
    assert proc.returncode != 0
    assert "BackendError" in proc.stderr and f"INSTANCING_THREADS={value!r}" in proc.stderr


def test_thread_count_is_set_from_the_environment():
    env = dict(os.environ, INSTANCING_THREADS="1", PYTHONPATH=_pythonpath())
    proc = subprocess.run([sys.executable, "-c", "import instancing, drjit; print(drjit.thread_count())"],
                          env=env, capture_output=True, text=True, timeout=120, cwd=str(REPO))
    assert proc.returncode == 0 and proc.stdout.strip() == "1", proc.stderr


def test_find_libllvm_returns_suitable_library():
    found = find_libllvm()
    if found is None:
        pytest.skip("no libLLVM >= MIN_LLVM_MAJOR installed in the standard locations")
    assert os.path.isfile(found)
    assert llvm_major_from_filename(found) >= MIN_LLVM_MAJOR


def test_loaded_llvm_is_recent_enough():
    if backend.BACKEND_NAME != "llvm":
        pytest.skip("not running on the LLVM backend")
    assert backend.dr.detail.llvm_version()[0] >= MIN_LLVM_MAJOR


def test_find_libllvm_picks_newest_suitable_file(tmp_path, monkeypatch):
    # Fake libraries (names only matter) in two folders searched by patched globs.
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    for name in ("libLLVM-15.so.1", "libLLVM-19.so.1", "libLLVM.so", "libLLVM-18.so"):
        (a / name).write_bytes(b"")
    (b / "libLLVM.so.21.1").write_bytes(b"")
    (b / "libLLVM-30.so").mkdir()  # a folder, not a library: ignored
    monkeypatch.setattr(backend, "_LLVM_SEARCH_GLOBS", (str(a / "libLLVM*.so*"), str(b / "libLLVM*")))
    assert find_libllvm() == str(b / "libLLVM.so.21.1")
    (b / "libLLVM.so.21.1").unlink()
    assert find_libllvm() == str(a / "libLLVM-19.so.1")
    (a / "libLLVM-19.so.1").unlink()
    assert find_libllvm() is None  # only 15, 18 and an unversioned name remain


@pytest.mark.skipif(BACKEND_NAME != "llvm", reason="checks the LLVM backend's generated code")
def test_device_array_is_aligned_and_its_float4_gathers_are_packet_loads():
    # Sizes on both sides of glibc's mmap threshold, where NumPy's own buffers are 16-byte
    # aligned: the copy must hold the values in 64-byte aligned storage, and a float4 gather
    # from it must compile to packet loads, not four scalar gathers.
    import numpy as np
    from instancing.core.backend import Array4f, Float, UInt32, dr, device_array
    for n in (64, 1 << 18):
        values = np.random.default_rng(n).random(n).astype(np.float32)
        array = device_array(Float, values)
        np.testing.assert_array_equal(np.asarray(array), values)
        assert np.from_dlpack(dr.detach(array)).ctypes.data % 64 == 0
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            dr.kernel_history()
            v = dr.gather(Array4f, array, dr.arange(UInt32, 16) * 3 % (n // 4))
            dr.eval(v.x + v.y * v.z - v.w)
            ir = "".join(k["ir"].getvalue() for k in dr.kernel_history()
                         if k["type"] == dr.KernelType.JIT)
        assert "gather_4x" in ir and "masked.gather" not in ir


def test_device_arrays_of_other_sizes_copy_with_the_same_kernel():
    """Each part's offset in the shared buffer is an opaque value: as a literal it made a kernel
    of its own per layout (3.4 ms of compilation for every new batch of NumPy rays)."""
    import numpy as np
    from instancing.core.backend import Float, dr, device_arrays
    hashes = []
    for sizes in ((5, 7, 9), (40, 3, 11), (23, 2, 6)):
        values = [np.arange(n, dtype=np.float32) + 100 * k for k, n in enumerate(sizes)]
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            dr.kernel_history()
            arrays = device_arrays(Float, *values)
            hashes.append({k["hash"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT})
        for array, expected in zip(arrays, values):
            np.testing.assert_array_equal(np.asarray(array), expected)
    assert len(hashes[0]) == 1 and hashes[0] == hashes[1] == hashes[2]
