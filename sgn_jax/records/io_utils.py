"""Small I/O helpers: atomic writes, JSON, content hashes.

Every artifact is written through :func:`atomic_write`, so an interrupted run never leaves a
half-written file under the final name.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import sgn_jax


@contextlib.contextmanager
def atomic_write(path: str | Path, mode: str = "wb") -> Iterator[IO[Any]]:
    """Open a temporary file next to ``path``; on success fsync it and rename it over ``path``.

    On an exception the temporary file is removed and ``path`` is left untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    # mkstemp creates the file 0600; give the artifact the usual permissions (0666 & ~umask).
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp_name, 0o666 & ~umask)
    try:
        with os.fdopen(fd, mode) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp_name, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp_name)
        raise


def write_json(path: str | Path, data: Any) -> None:
    """Write ``data`` as indented JSON, atomically."""
    with atomic_write(path, "w") as fh:
        json.dump(data, fh, indent=2, sort_keys=True, default=json_default)
        fh.write("\n")


def append_jsonl(path: str | Path, record: Any) -> None:
    """Append ``record`` as one JSON line and fsync it: a log that a killed run resumes from
    (:func:`read_jsonl`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as fh:
        fh.write(json.dumps(record, default=json_default) + "\n")
        fh.flush()
        os.fsync(fh.fileno())


def read_jsonl(path: str | Path) -> list[Any]:
    """The records of a JSON-lines log (none if it does not exist); a line cut by a kill is
    skipped, so the run that wrote it is redone."""
    path = Path(path)
    if not path.exists():
        return []
    records = []
    for line in path.read_text().splitlines():
        try:
            records.append(json.loads(line))
        except ValueError:
            continue
    return records


def json_default(obj: Any) -> Any:
    """``default=`` hook for ``json.dump(s)``: numpy scalars and arrays become Python numbers
    and lists, paths strings; anything else raises TypeError naming its type."""
    import numpy as np

    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"value of type {type(obj).__name__} is not JSON serialisable")


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


def _git(*args: str) -> subprocess.CompletedProcess[str]:
    """Run ``git *args`` in the source tree (5 s limit), capturing text output."""
    return subprocess.run(["git", *args], cwd=Path(__file__).resolve().parent,
                          capture_output=True, text=True, timeout=5)


def git_commit() -> str:
    """The current git commit of the source tree, or 'unknown' outside a checkout."""
    try:
        out = _git("rev-parse", "--short", "HEAD")
        dirty = _git("status", "--porcelain", "--untracked-files=no")
        if out.returncode == 0:
            return out.stdout.strip() + ("-dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        pass
    return "unknown"


def machine_info() -> dict[str, Any]:
    """Where a timing was taken: platform, CPU, cores used, load, versions, commit and date.

    Shared by the benchmark scripts and ``sgn-jax demo`` so that every recorded number names
    its machine the same way.
    """
    import platform
    import time

    import jax

    affinity = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
    load = os.getloadavg()
    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "cores_used": len(affinity) if affinity else os.cpu_count(),
        "load_average": [round(x, 2) for x in load],
        "load_average_start": load[0],
        "python": platform.python_version(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "sgn_jax": sgn_jax.__version__,
        "commit": git_commit(),
        "date": time.strftime("%Y-%m-%d %H:%M"),
    }
