"""The user cache: JAX's persistent compilation cache and the settled DEM packings.

Both live under one directory, :func:`cache_root`:

- ``$SGN_JAX_CACHE_DIR`` if set, else ``$XDG_CACHE_HOME/sgn_jax``, else ``~/.cache/sgn_jax``;
- ``jax/``: compiled XLA programs (JAX's own persistent cache, keyed by JAX on the program,
  the jax/jaxlib version and the machine), so a second ``sgn-jax dem`` or a second design-study
  session skips most compilation;
- ``settled/``: settled DEM states (one ``.npz`` per jar, balls, material, DEM settings and
  seed; the motion only translates them), so a short DEM run does not settle every time.

Set ``SGN_JAX_NO_CACHE=1`` to switch both off (nothing is read or written). Deleting the
directory is always safe. The CLI and :mod:`sgn_jax.api` enable the cache; a library user who
imports only the core modules decides with :func:`enable_compilation_cache`.
"""

from __future__ import annotations

import os
from pathlib import Path

ENV_DIR = "SGN_JAX_CACHE_DIR"
ENV_OFF = "SGN_JAX_NO_CACHE"

# Programs that compile faster than this are not worth a disk round trip.
MIN_COMPILE_TIME_S = 0.5


def cache_enabled() -> bool:
    """False when ``SGN_JAX_NO_CACHE`` is set to anything but '' or '0'."""
    return os.environ.get(ENV_OFF, "") in ("", "0")


def cache_root() -> Path:
    """The cache directory (not created here)."""
    if os.environ.get(ENV_DIR):
        return Path(os.environ[ENV_DIR]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "sgn_jax"


def enable_compilation_cache() -> Path | None:
    """Point JAX's persistent compilation cache at ``cache_root()/jax``; returns the directory,
    or None when the cache is off. Idempotent; a directory that cannot be created leaves JAX
    uncached rather than failing."""
    if not cache_enabled():
        return None
    import jax

    directory = cache_root() / "jax"
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", str(directory))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_TIME_S)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return directory


def settled_dir() -> Path | None:
    """Where settled DEM states are kept, or None when the cache is off."""
    return cache_root() / "settled" if cache_enabled() else None


__all__ = ["cache_enabled", "cache_root", "enable_compilation_cache", "settled_dir"]
