"""Build and register the native CPU visibility kernel (``csrc/raster.cc``) through ``jax.ffi``.

The kernel is compiled on first use with the system C++ compiler against the XLA FFI headers
that ship with jaxlib, and cached under ``$XDG_CACHE_HOME/diffshade`` (default
``~/.cache/diffshade``), keyed by the source, the jaxlib version and the compiler flags. If no
compiler is available the renderer falls back to the pure-JAX path (``backend="jax"``), which
computes exactly the same visibility.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

import jax
import jaxlib

_SOURCE = Path(__file__).parent / "csrc" / "raster.cc"
_FLAGS = [
    "-O3",
    "-std=c++17",
    "-shared",
    "-fPIC",
    "-ffp-contract=off",
    "-fno-fast-math",
    "-fno-trapping-math",
    "-pthread",
]
_TARGET = "diffshade_raster"
_lock = threading.Lock()
_state: dict = {}


class NativeUnavailable(RuntimeError):
    """The native kernel could not be built or loaded."""


def _cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "diffshade"


def _build() -> Path:
    src = _SOURCE.read_bytes()
    cxx = os.environ.get("CXX") or shutil.which("g++") or shutil.which("c++") or shutil.which("clang++")
    if cxx is None:
        raise NativeUnavailable("no C++ compiler found (set CXX or install g++)")
    key = hashlib.sha256(src + jaxlib.__version__.encode() + " ".join(_FLAGS + [cxx]).encode()).hexdigest()[:16]
    out = _cache_dir() / f"raster-{key}.so"
    if out.exists():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out.parent) as tmp:
        tmp_so = Path(tmp) / out.name
        cmd = [cxx, *_FLAGS, "-I", jax.ffi.include_dir(), str(_SOURCE), "-o", str(tmp_so)]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            raise NativeUnavailable(f"compiling {_SOURCE.name} failed:\n{proc.stderr[-2000:]}")
        os.replace(tmp_so, out)  # atomic: concurrent builders never see a half-written file
    return out


def ensure_registered() -> str:
    """Build (once) and register the kernel; returns the FFI target name or raises NativeUnavailable."""
    with _lock:
        if "error" in _state:
            raise NativeUnavailable(_state["error"])
        if "lib" not in _state:
            try:
                lib = ctypes.cdll.LoadLibrary(str(_build()))
                jax.ffi.register_ffi_target(_TARGET, jax.ffi.pycapsule(lib.DiffshadeRaster), platform="cpu")
            except (OSError, NativeUnavailable, AttributeError) as exc:
                _state["error"] = str(exc)
                raise NativeUnavailable(str(exc)) from exc
            _state["lib"] = lib
    return _TARGET


def available() -> bool:
    """Whether the native kernel can be used here: it builds, and JAX's default device is the CPU
    (it is a CPU kernel)."""
    if jax.default_backend() != "cpu":
        return False
    try:
        ensure_registered()
    except NativeUnavailable:
        return False
    return True
