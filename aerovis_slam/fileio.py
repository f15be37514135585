"""Writing outputs safely: atomic writes and checked output folders (shared by every tool).

An atomic write goes to a uniquely named temporary file beside the target (same file system), is
made world-readable like an ordinary file, and is renamed over the target with ``os.replace``; a
crash or Ctrl-C at any point leaves either the old file or the new one, never half of one, and no
temporary file behind. A folder is built the same way (:func:`make_build_dir`, renamed when
complete); :func:`remove_abandoned` deletes the build folders of killed processes.

Example:
    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> atomic_write_json(d / "a.json", {"x": 1}).read_text()
    '{\\n  "x": 1\\n}\\n'
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import sys
import tempfile
import time
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


# A build folder with no owner in its name (written by an earlier version) or another host's counts
# as abandoned after this long without a change: a live build writes its files every few seconds.
_UNOWNED_QUIET_S = 3600.0


def _host() -> str:
    """This machine's name as it appears in temporary folder names (letters, digits, ``_``, ``-``)."""
    return re.sub(r"[^A-Za-z0-9_-]", "_", socket.gethostname()) or "host"


def make_build_dir(final: str | os.PathLike) -> Path:
    """A new private folder beside ``final`` to build it in, then rename to ``final``:
    ``.<final name>.<host>-<pid>.<random>.tmp``, so that :func:`remove_abandoned` can tell whether
    the process building it still runs."""
    final = Path(final)
    return Path(tempfile.mkdtemp(prefix=f".{final.name}.{_host()}-{os.getpid()}.", suffix=".tmp", dir=final.parent))


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


def _newest_change(folder: Path) -> float:
    """Latest modification time (s since the epoch) of ``folder`` and the files in it."""
    times = [folder.stat().st_mtime]
    for f in folder.iterdir():
        try:
            times.append(f.stat().st_mtime)
        except OSError:  # renamed meanwhile by its generator
            pass
    return max(times)


def remove_abandoned(final: str | os.PathLike) -> list[Path]:
    """Delete the build folders of ``final`` (:func:`make_build_dir`) whose process has ended; returns them.

    A process killed outright (SIGKILL, or SIGTERM, which runs no Python cleanup) cannot delete its
    build folder, which may hold gigabytes; callers sweep before using or building ``final``.
    A folder named by :func:`make_build_dir` on this host is abandoned when its process no longer
    exists (a live one, or a new process that reused the id, keeps it: erring towards keeping). One
    from another host, or from a version that did not record its owner, is abandoned when nothing
    in it has changed for an hour. Each removal is reported on stderr with its size. (Containers that
    share one cache folder must not share a host name, or one could take another's live build for a
    dead process's: their process ids are separate.)
    """
    final = Path(final)
    root = final.parent
    if not root.is_dir():
        return []
    host = _host()
    now = time.time()
    owned = re.compile(re.escape(f".{final.name}.") + r"(?P<host>[A-Za-z0-9_-]+)-(?P<pid>\d+)\.")
    removed = []
    for d in sorted(root.glob(f".{final.name}.*.tmp")):
        try:
            m = owned.match(d.name)
            if m and m["host"] == host:
                if _pid_alive(int(m["pid"])):
                    continue
            elif now - _newest_change(d) < _UNOWNED_QUIET_S:
                continue
            size = sum(f.stat().st_size for f in d.iterdir() if f.is_file())
        except OSError:  # removed or renamed by its owner meanwhile
            continue
        shutil.rmtree(d, ignore_errors=True)
        if not d.exists():
            removed.append(d)
            print(f"aerovis: removed {d} ({size / 2**20:.1f} MiB), left by a build that was killed before it "
                  "finished", file=sys.stderr)
    return removed
