"""Build and register the native CPU kernels (``csrc/raster.cc``: visibility; ``csrc/shade.cc``:
shading, :mod:`diffshade._fast`; ``csrc/normals.cc``: vertex normals) through ``jax.ffi``.

The kernels are compiled on first use, into one library, with the system C++ compiler against the
XLA FFI headers that ship with jaxlib, and cached under ``$XDG_CACHE_HOME/diffshade`` (default
``~/.cache/diffshade``), keyed by the sources, the jaxlib version and the compiler flags. If no
compiler is available the renderer falls back to the pure-JAX path (``backend="jax"``), which
computes exactly the same visibility and the same shading (to float32 rounding).
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
import threading
import warnings
from pathlib import Path

import jax
import jaxlib

_CSRC = Path(__file__).parent / "csrc"
_SOURCES = [_CSRC / "raster.cc", _CSRC / "shade.cc", _CSRC / "normals.cc"]
_HEADERS = [_CSRC / "parallel.h", _CSRC / "math_lanes.h"]
_FLAGS = [
    "-O3",
    "-std=c++17",
    "-shared",
    "-fPIC",
    "-ffp-contract=off",
    "-fno-fast-math",
    "-fno-trapping-math",
    "-fno-math-errno",
    "-pthread",
]
# FFI target name -> the symbol of its handler in the library
_TARGETS = {
    "diffshade_raster": "DiffshadeRaster",
    "diffshade_shade": "DiffshadeShade",
    "diffshade_shade_partials": "DiffshadeShadePartials",
    "diffshade_normals": "DiffshadeNormals",
}
_lock = threading.Lock()
_state: dict = {}


class NativeUnavailable(RuntimeError):
    """The native kernel could not be built or loaded."""


def _cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "diffshade"


def build_library(stem: str, sources: list[Path], headers: list[Path] = (), ffi: bool = False, libs=()) -> Path:
    """Compile ``sources`` into the shared library ``<stem>-<key>.so`` in the cache (once: the key
    hashes the sources, the headers, the jaxlib version and the flags), against the XLA FFI headers
    where ``ffi``, linked with ``libs`` (``-l`` flags); returns its path or raises NativeUnavailable
    with the compiler's error."""
    src = b"".join(p.read_bytes() for p in [*sources, *headers])
    cxx = os.environ.get("CXX") or shutil.which("g++") or shutil.which("c++") or shutil.which("clang++")
    if cxx is None:
        raise NativeUnavailable("no C++ compiler found (set CXX or install g++)")
    key = hashlib.sha256(
        src + jaxlib.__version__.encode() + " ".join(_FLAGS + list(libs) + [cxx]).encode()
    ).hexdigest()[:16]
    out = _cache_dir() / f"{stem}-{key}.so"
    if out.exists():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out.parent) as tmp:
        tmp_so = Path(tmp) / out.name
        include = ["-I", jax.ffi.include_dir()] if ffi else []
        cmd = [cxx, *_FLAGS, *include, *map(str, sources), *libs, "-o", str(tmp_so)]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            names = " and ".join(p.name for p in sources)
            raise NativeUnavailable(f"compiling {names} failed:\n{proc.stderr[-2000:]}")
        os.replace(tmp_so, out)  # atomic: concurrent builders never see a half-written file
    return out


def _build() -> Path:
    return build_library("kernels", _SOURCES, _HEADERS, ffi=True)


def ensure_registered(target: str = "diffshade_raster") -> str:
    """Build (once) and register the kernels; returns ``target`` (an FFI target name: the
    visibility kernel's by default, or ``"diffshade_shade"``) or raises NativeUnavailable."""
    with _lock:
        if "error" in _state:
            raise NativeUnavailable(_state["error"])
        if "lib" not in _state:
            try:
                lib = ctypes.cdll.LoadLibrary(str(_build()))
                for name, symbol in _TARGETS.items():
                    jax.ffi.register_ffi_target(name, jax.ffi.pycapsule(getattr(lib, symbol)), platform="cpu")
            except (OSError, NativeUnavailable, AttributeError) as exc:
                _state["error"] = str(exc)
                raise NativeUnavailable(str(exc)) from exc
            _state["lib"] = lib
    return target


def available() -> bool:
    """Whether the native kernel can be used here: it builds, and JAX's default device is the CPU
    (it is a CPU kernel). On the CPU, a kernel that does not build is said once, as a warning
    that names why (a compiler's error, no compiler)."""
    if jax.default_backend() != "cpu":
        return False
    try:
        ensure_registered()
    except NativeUnavailable as exc:
        if not _state.get("warned"):  # (once: the renders that follow all take the JAX stages)
            _state["warned"] = True
            warnings.warn(
                "diffshade's native CPU kernels are unavailable, so renders take the JAX stages (the same "
                f"images, several times slower): {exc}",
                RuntimeWarning,
                stacklevel=2,
            )
        return False
    return True
