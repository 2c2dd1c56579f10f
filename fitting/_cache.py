"""Compiled programs, cached per problem structure (the :data:`CACHE_SIZE` most recently used),
and JAX's persistent compilation cache.

Each compiled program keeps its machine code mapped, and Linux allows a process a bounded number
of memory mappings: unbounded, a session that fits many structures runs out (design notes:
docs/fit-design-notes.md, "The compiled-program cache")."""

from __future__ import annotations

import gc
import os
import threading
import time
from collections import OrderedDict

import jax
import numpy as np

CACHE_SIZE = 16
CACHE_BYTES = 2 << 30  # the persistent cache's bound on disk
_CACHE: OrderedDict = OrderedDict()
_STATS = {"hits": 0, "misses": 0}


def cache_info() -> dict:
    """Hits, misses (compiles), current size and capacity of the compiled-program cache."""
    return dict(_STATS, size=len(_CACHE), capacity=CACHE_SIZE)


def _shapes(args) -> tuple:
    leaves, treedef = jax.tree.flatten(args)
    # (a leaf may be a Python number: its type stands for the dtype it is traced with)
    return treedef, tuple(
        (np.shape(x), getattr(x, "dtype", type(x).__name__), getattr(x, "sharding", None)) for x in leaves
    )


# XLA's options for a program of few pixels: its older CPU code emitters and LLVM's first
# optimisation level compile a one-view fit ~1.6x faster, and what they emit solves as fast there
# (level 0 compiles faster still, but solves 2-3x slower and rounds differently enough from the
# target's render to make one suite case a false success: docs/design.md, "Compile speed against
# run speed").
FAST_COMPILE = {"xla_cpu_use_fusion_emitters": False, "xla_backend_optimization_level": 1}
FAST_COMPILE_PIXELS = 1 << 20
# A program that loops over stacked views (fitting._problem.Problem.map_views) is compiled without
# XLA's loop-invariant code motion: inside the solve's loop it has little to hoist (each view's
# geometry is the view loop's), and over its nested loops the pass and the simplifications it
# sets off took a third of the HLO passes; measured, a photometric capture of 8 views compiled
# in 1.08 against 1.33 s and ran 13.9 against 15.0 ms per evaluation, 8 views of 256² of the
# default scene (fast and optimised, with and without per-view exposures) compiled 0.02-0.4 s
# faster and ran within 3 % (docs/design.md, "Compile speed against run speed").
LOOP_OVER_VIEWS = {"xla_disable_hlo_passes": "while-loop-invariant-code-motion"}
COMPILE_MODES = ("auto", "fast", "optimised")


# A program a fit runs once or twice (a texture map's design matrix, where no other parameter is
# free): LLVM unoptimised. The floor case of the map fits (4 views of 256², float64) compiled its
# program in 0.66 against 1.27-1.40 s of XLA's time, and ran it in 0.28 against 0.20 s.
ONCE = {"xla_cpu_use_fusion_emitters": False, "xla_backend_optimization_level": 0}


def compile_mode(pixels: int, once: bool = False) -> str:
    """``"fast"``, ``"optimised"`` or ``"once"``: how a fit over ``pixels`` pixels (all views)
    compiles a program it runs many times, or (``once``) one or twice. ``$DIFFSHADE_COMPILE``
    (``fast``, ``optimised`` or ``auto``, the default) chooses; ``auto`` compiles fast up to
    :data:`FAST_COMPILE_PIXELS`, where the compile saved outweighs the slower solve, and a
    program run once unoptimised (:data:`ONCE`) unless ``optimised`` is asked for."""
    mode = os.environ.get("DIFFSHADE_COMPILE", "auto").strip().lower() or "auto"
    if mode not in COMPILE_MODES:
        raise ValueError(f"$DIFFSHADE_COMPILE must be one of {', '.join(COMPILE_MODES)}, got {mode!r}")
    if once and mode != "optimised":
        return "once"
    if mode == "auto":
        return "fast" if pixels <= FAST_COMPILE_PIXELS else "optimised"
    return mode


def compiled(prob, what: str, fn, *args, extra=(), once: bool = False, meanwhile=None):
    """``jax.jit(fn).lower(*args).compile()``, cached on the problem's structure (the
    :data:`CACHE_SIZE` most recently used), compiled as :func:`compile_mode` says for the
    problem's pixels (``once``: a program the fit runs once or twice); returns ``(compiled,
    compile_seconds)`` (0 when cached). ``meanwhile``: see :func:`program`."""
    pset = prob.pset
    structure = (tuple(pset.labels), tuple(p.path for p in pset.params), tuple(pset.sizes), prob.opts, *extra)
    mode = compile_mode(sum(int(vd.target.shape[0]) for vd in prob.data), once)
    options = dict(FAST_COMPILE) if mode == "fast" else dict(ONCE) if mode == "once" else {}
    if prob.stacked and len(prob.data) > 1:
        options.update(LOOP_OVER_VIEWS)
    return program((what, mode, *structure), fn, *args, options=options or None, meanwhile=meanwhile)


def program(key: tuple, fn, *args, options: dict | None = None, meanwhile=None):
    """``jax.jit(fn).lower(*args).compile()`` for ``fn`` (a function of arrays only, its static
    configuration closed over and named in ``key``), cached on ``key`` and the arguments'
    shapes in the one bounded cache; returns ``(compiled, compile_seconds)``.

    ``meanwhile``: host work the caller needs next that does not wait on the program, run in a
    thread while XLA compiles (XLA lets go of the GIL and keeps about one core busy; the
    tracing before it holds the GIL): afterwards, or where the program is cached, it has run.
    What it raises is dropped: the caller meets it again where it needs the work.

    Every per-structure program a fit runs goes through here, not through ``jax.jit`` of a
    module-level function: JAX's own cache of those keeps up to 8,192 executables alive for
    the life of the process (with their mapped machine code), so a session fitting many
    structures would grow without bound."""
    key = (*key, *_shapes(args))
    if key in _CACHE:
        _STATS["hits"] += 1
        _CACHE.move_to_end(key)
        _quietly(meanwhile)
        return _CACHE[key], 0.0
    _STATS["misses"] += 1
    t0 = time.perf_counter()
    # Tracing makes hundreds of thousands of objects, and Python's cyclic collector walks the
    # growing heap again and again meanwhile: off for the trace (measured, suite structures:
    # tracing and lowering 0.05-0.1 s faster of 0.4-0.55 s); what it would free is freed after.
    collecting = gc.isenabled()
    gc.disable()
    try:
        lowered = jax.jit(fn).lower(*args)
    finally:
        if collecting:
            gc.enable()
    beside = threading.Thread(target=_quietly, args=(meanwhile,), name="diffshade-meanwhile") if meanwhile else None
    if beside is not None:
        beside.start()
    try:
        try:
            exe = lowered.compile(compiler_options=options)
        except Exception:  # an XLA that does not know an option: its defaults
            if not options:
                raise
            exe = lowered.compile()
    finally:
        if beside is not None:
            beside.join()
    dt = time.perf_counter() - t0
    _CACHE[key] = exe
    while len(_CACHE) > CACHE_SIZE:
        _CACHE.popitem(last=False)
    if _VERBOSE_COMPILE:
        print(f"compiled {key[0]} in {dt:.2f} s")
    return exe, dt


def _quietly(fn):
    if fn is None:
        return
    try:
        fn()
    except Exception:  # (met again by the caller, where it needs what fn makes)
        pass


def run(key: tuple, fn, *args):
    """``fn(*args)`` through :func:`program`'s cache, compiled as a program run once
    (:data:`ONCE`, unless ``$DIFFSHADE_COMPILE`` asks for ``optimised``): what goes through here
    prepares a fit (a view's visibility, its silhouette's edges), once per view. Measured, the
    visibility of a 256² view compiled in 0.19-0.22 against 0.36-0.37 s, and ran in 6 against 5 ms."""
    mode = compile_mode(0, once=True)
    return program((*key, mode), fn, *args, options=dict(ONCE) if mode == "once" else None)[0](*args)


_VERBOSE_COMPILE = False


def enable_compilation_cache(path: str | None = None) -> str:
    """Turn on JAX's persistent compilation cache (default ``~/.cache/diffshade/xla``, or
    ``$DIFFSHADE_CACHE``): a second run of a fit of the same structure loads its programs
    instead of compiling them."""
    path = (
        path or os.environ.get("DIFFSHADE_CACHE") or os.path.join(os.path.expanduser("~"), ".cache", "diffshade", "xla")
    )
    os.makedirs(path, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", path)
    # bounded (least recently used entries evicted): JAX then locks each read and write, so that
    # concurrent runs never read an entry another is still writing
    jax.config.update("jax_compilation_cache_max_size", CACHE_BYTES)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.1)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path
