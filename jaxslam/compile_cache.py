"""JAX's persistent compilation cache for the command line: a run compiles its step once per
machine, not once per process.

Only the command line turns it on (:func:`enable`); ``import jaxslam`` leaves JAX's settings
alone. The folder is ``$JAXSLAM_CACHE_DIR`` if set, else ``$XDG_CACHE_HOME/jaxslam/jax``, else
``~/.cache/jaxslam/jax``; ``JAXSLAM_CACHE_DIR=off`` (or ``jaxslam map --no-cache``) turns it
off. A folder that cannot be created or written is warned of (one line) and the run goes on
without the cache. Where JAX's own ``JAX_COMPILATION_CACHE_DIR`` is set and
``$JAXSLAM_CACHE_DIR`` is not, JAX's folder is kept.

The cache holds compiled executables, which JAX loads and runs: keep it in a folder only you
can write (the default one is made private, mode 0700).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import jax

ENV = "JAXSLAM_CACHE_DIR"
"""The environment variable that names the folder, or turns the cache off (``off``)."""
OFF = ("off", "0", "none", "false", "no")
"""Values of :data:`ENV` that turn the cache off (any case)."""
MIN_COMPILE_SECONDS = 0.0
"""Compilations shorter than this are not written. JAX's default, 1 s, leaves out a run's
smaller functions, and any threshold makes what is cached depend on the machine's load; JAX
looks every compilation up in the cache whatever the threshold, so writing them all costs only
the disk (a few MB for a run)."""


def cache_dir(environ=None) -> Path | None:
    """The folder the command line caches compilations in, or None when turned off."""
    environ = os.environ if environ is None else environ
    value = environ.get(ENV)
    if value is not None and value.strip():
        return None if value.strip().lower() in OFF else Path(value).expanduser()
    base = environ.get("XDG_CACHE_HOME")
    return (Path(base).expanduser() if base else Path.home() / ".cache") / "jaxslam" / "jax"


def _writable(folder: Path) -> str | None:
    """None if ``folder`` exists (made if missing, private) and a file can be written in it; else why not."""
    try:
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".probe-"):
            pass
    except OSError as err:
        return err.strerror or type(err).__name__
    return None


def enable(disabled: bool = False, environ=None) -> tuple[str | None, str | None]:
    """Turn JAX's persistent compilation cache on for this process (before its first compilation).

    Returns ``(folder, warning)``: the folder in use (None when off) and a one-line warning when
    the folder could not be used (the run goes on without the cache), else None.
    """
    environ = os.environ if environ is None else environ
    folder = None if disabled else cache_dir(environ)
    if folder is not None and not (environ.get(ENV) or "").strip() and jax.config.jax_compilation_cache_dir:
        return jax.config.jax_compilation_cache_dir, None  # the user's own JAX setting (JAX_COMPILATION_CACHE_DIR)
    problem = None if folder is None else _writable(folder)
    if folder is None or problem is not None:
        if jax.config.jax_compilation_cache_dir:  # off means off, JAX's own setting included
            jax.config.update("jax_enable_compilation_cache", False)
        if problem is None:
            return None, None
        return None, (f"the compilation cache folder {folder} cannot be used ({problem}); running without it "
                      f"(every run compiles anew; set {ENV} to a writable folder, or {ENV}=off)")
    jax.config.update("jax_enable_compilation_cache", True)
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECONDS)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return str(folder), None
