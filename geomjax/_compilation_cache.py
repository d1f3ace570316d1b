"""Keep compiled programs between processes: JAX's persistent compilation cache in one call.

The first call of an op in a fresh process traces and compiles its program (seconds on a small
CPU), and without a persistent cache every process pays that again. Two caches matter:

* JAX's persistent compilation cache keeps XLA executables on disk, keyed by the lowered program
  (and the jax version, backend, devices and compile options). :func:`enable_compilation_cache`
  turns it on. A later process still traces the op (that is how it finds the key), then loads
  the executable instead of compiling it.
* Warp's kernel cache (``~/.cache/warp``, or ``WARP_CACHE_PATH``) keeps the compiled Warp modules
  (kernels built from their source), always on. A program with a Warp call needs both: the cached
  executable calls the Warp FFI target that the trace registered again in this process.

Programs are safe to reuse across processes: the per-process state they refer to (Warp's
launch descriptors, geomjax's check messages) is keyed by values that are part of the lowered
program, and the trace in the new process records it again before the executable runs.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax

__all__ = ["default_compilation_cache_dir", "enable_compilation_cache"]


def default_compilation_cache_dir() -> Path:
    """``$GEOMJAX_CACHE_DIR``, else JAX's own ``$JAX_COMPILATION_CACHE_DIR`` (a folder the user
    already chose for JAX), else ``$XDG_CACHE_HOME/geomjax/jax`` (``~/.cache/geomjax/jax``)."""
    for variable in ("GEOMJAX_CACHE_DIR", "JAX_COMPILATION_CACHE_DIR"):
        if os.environ.get(variable):
            return Path(os.environ[variable])
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "geomjax" / "jax"


def enable_compilation_cache(path: str | os.PathLike[str] | None = None, *, min_compile_time_secs: float = 0.0) -> Path:
    """Turn on JAX's persistent compilation cache in ``path`` for this process.

    Call it once, early (before the programs you want kept are compiled; programs compiled
    earlier in the process are not written back). It sets JAX's global configuration
    (``jax_compilation_cache_dir`` and ``jax_persistent_cache_min_compile_time_secs``), so it
    applies to every program of the process, not only geomjax's. Only trusted users may write to
    ``path``: JAX runs what it finds there.

    Args:
        path: the cache directory, created if missing; ``None`` uses
            :func:`default_compilation_cache_dir`.
        min_compile_time_secs: programs that compile faster than this are not written (JAX's
            default is 1 s; geomjax's first calls are many programs of 0.05-1 s each, so the
            default here keeps them all).

    Returns:
        The cache directory.

    Example:
        >>> import tempfile, geomjax
        >>> directory = geomjax.enable_compilation_cache(tempfile.mkdtemp())
        >>> directory.is_dir()
        True
    """
    directory = Path(path) if path is not None else default_compilation_cache_dir()
    directory.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(directory))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time_secs))
    return directory
