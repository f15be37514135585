"""Writing outputs safely: atomic writes and checked output folders (shared by every tool).

An atomic write goes to a uniquely named temporary file beside the target (same file system), is
made world-readable like an ordinary file, and is renamed over the target with ``os.replace``; a
crash or Ctrl-C at any point leaves either the old file or the new one, never half of one, and no
temporary file behind.

Example:
    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> atomic_write_json(d / "a.json", {"x": 1}).read_text()
    '{\\n  "x": 1\\n}\\n'
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .errors import DataError


def atomic_write(path: str | os.PathLike, write: Callable[[Path], Any]) -> Path:
    """Call ``write(tmp)`` to fill a temporary file beside ``path``, then rename it to ``path``.

    ``write`` receives the temporary path (its suffix is ``.partial``, so writers that infer a
    format from the name, such as matplotlib's ``savefig``, must be told the format). The parent
    folder is created. Returns ``path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".partial", dir=path.parent)
    os.close(fd)
    try:
        write(Path(tmp))
        os.chmod(tmp, 0o644)  # mkstemp makes it private; outputs are ordinary files
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    return atomic_write(path, lambda p: p.write_text(text, encoding="utf-8"))


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically."""
    return atomic_write(path, lambda p: p.write_bytes(data))


def atomic_write_json(path: str | os.PathLike, obj: Any, *, indent: int = 2, default: Callable | None = None) -> Path:
    """Write ``obj`` as JSON (a trailing newline) to ``path`` atomically; ``default`` as in :func:`json.dumps`."""
    return atomic_write_text(path, json.dumps(obj, indent=indent, default=default) + "\n")


def prepare_out_dir(out_dir: str | os.PathLike) -> Path:
    """Create ``out_dir`` if needed and check that it is writable.

    Raises:
        DataError: naming the folder, when it cannot be created or written.
    """
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DataError(out_dir, f"cannot create output folder ({exc.strerror})") from None
    if not os.access(out_dir, os.W_OK | os.X_OK):
        raise DataError(out_dir, "output folder is not writable")
    return out_dir
