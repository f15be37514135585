"""Generate a preset once, reuse it afterwards (for the training data module).

The cache root is ``$AEROVIS_CACHE/sim`` when the environment variable is set, else
``~/.cache/aerovis/sim``; a preset lives in ``<root>/<name>-seed<seed>-v<SIM_VERSION>/`` (a new
simulator version, which changes the data, regenerates instead of reusing stale files). Generation goes
into a hidden temporary folder beside it that is renamed when complete, so an interrupted
run never leaves a folder that looks finished, and two concurrent callers end with one copy.

Example:
    >>> import tempfile
    >>> root = tempfile.mkdtemp()
    >>> p = ensure_preset("tiny", cache_dir=root, progress=False)
    >>> p.name, (p / "summary.json").is_file(), ensure_preset("tiny", cache_dir=root) == p
    ('tiny-seed0-v1', True, True)
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

from ..errors import DataError


def cache_root() -> Path:
    """``$AEROVIS_CACHE/sim`` or ``~/.cache/aerovis/sim``."""
    env = os.environ.get("AEROVIS_CACHE")
    return (Path(env).expanduser() if env else Path.home() / ".cache" / "aerovis") / "sim"


def ensure_preset(name: str, cache_dir: str | None = None, seed: int = 0, *, progress: bool = True,
                  workers: int | None = None) -> Path:
    """The folder of preset ``name`` generated with ``seed``, generating it on first use.

    Args:
        name: preset name (``train``, ``bench``, ``tiny``).
        cache_dir: folder that holds ``<name>-seed<seed>-v<SIM_VERSION>/`` (default :func:`cache_root`).
        seed: preset seed.
        progress: show progress bars while generating.
        workers: sequences generated at a time, one process each (None: one per CPU core).

    Returns:
        The complete folder (``*.h5`` and ``summary.json``).

    Raises:
        DataError: unknown preset or unwritable cache folder.
    """
    from .cli import run_preset
    from .presets import preset_specs
    from .simulator import SIM_VERSION

    preset_specs(name, seed)  # validate the name before touching the disk
    root = Path(cache_dir).expanduser() if cache_dir is not None else cache_root()
    final = root / f"{name}-seed{seed}-v{SIM_VERSION}"
    if (final / "summary.json").is_file():
        return final
    try:
        root.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".tmp", dir=root))
    except OSError as exc:
        raise DataError(root, f"cache folder is not writable ({exc.strerror})") from None
    try:
        run_preset(name, tmp, seed=seed, progress=progress, workers=workers)
        os.chmod(tmp, 0o755)  # mkdtemp makes it private; the finished cache is ordinary shared data
        try:
            os.rename(tmp, final)
        except OSError:
            if not (final / "summary.json").is_file():  # not a concurrent winner: a real error
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return final
