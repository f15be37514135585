"""Generate a preset once, reuse it afterwards (for the training data module).

The cache root is ``$AEROVIS_CACHE/sim`` when the environment variable is set, else
``~/.cache/aerovis/sim``; a preset lives in ``<root>/<name>-seed<seed>-v<SIM_VERSION>/``, with
``r<revision>`` appended from a preset's second revision on (:func:`preset_dir`; a new simulator
version or preset revision, which changes the data, regenerates instead of reusing stale files). Generation goes
into a hidden temporary folder beside it that is renamed when complete, so an interrupted
run never leaves a folder that looks finished, and two concurrent callers end with one copy.
A run killed outright (SIGKILL, or SIGTERM from a job scheduler or ``timeout``: no Python cleanup
runs) leaves its temporary folder behind, up to the preset's size (1.5 GB for ``train``); every
later call for the same preset removes such folders once their process has ended
(:func:`aerovis_slam.fileio.remove_abandoned`).

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
from pathlib import Path

from ..errors import DataError
from ..fileio import make_build_dir, remove_abandoned


def cache_root() -> Path:
    """``$AEROVIS_CACHE/sim`` or ``~/.cache/aerovis/sim``."""
    env = os.environ.get("AEROVIS_CACHE")
    return (Path(env).expanduser() if env else Path.home() / ".cache" / "aerovis") / "sim"


def preset_dir(name: str, seed: int = 0, cache_dir: str | os.PathLike | None = None) -> Path:
    """Where preset ``name`` of ``seed`` is cached (whether or not it has been generated yet):
    ``<root>/<name>-seed<seed>-v<SIM_VERSION>`` plus ``r<revision>`` for a preset revised since
    (:data:`~aerovis_slam.sim.presets.PRESET_REVISIONS`; ``bench-seed0-v1r2``).

    Raises:
        DataError: for an unknown preset.
    """
    from .presets import PRESET_REVISIONS, preset_specs
    from .simulator import SIM_VERSION

    preset_specs(name, seed)  # validate the name
    root = Path(cache_dir).expanduser() if cache_dir is not None else cache_root()
    revision = PRESET_REVISIONS[name]
    return root / (f"{name}-seed{seed}-v{SIM_VERSION}" + (f"r{revision}" if revision > 1 else ""))


def ensure_preset(name: str, cache_dir: str | None = None, seed: int = 0, *, progress: bool = True,
                  workers: int | None = None) -> Path:
    """The folder of preset ``name`` generated with ``seed``, generating it on first use.

    Args:
        name: preset name (``train``, ``bench``, ``tiny``).
        cache_dir: folder that holds the preset's folder (:func:`preset_dir`; default :func:`cache_root`).
        seed: preset seed.
        progress: show progress bars while generating.
        workers: sequences generated at a time, one process each (None: one per CPU core).

    Returns:
        The complete folder (``*.h5`` and ``summary.json``).

    Raises:
        DataError: unknown preset or unwritable cache folder.
    """
    from .cli import run_preset

    final = preset_dir(name, seed, cache_dir)  # validates the name before touching the disk
    root = final.parent
    remove_abandoned(final)
    if (final / "summary.json").is_file():
        _note_opencv_mismatch(final)
        return final
    try:
        root.mkdir(parents=True, exist_ok=True)
        tmp = make_build_dir(final)
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


_noted: set[Path] = set()


def _note_opencv_mismatch(folder: Path) -> None:
    """Say once per folder, on stderr, when a cached preset was generated with another OpenCV.

    The simulator draws its "text" textures with ``cv2.putText``, and OpenCV 5.1 draws them
    differently from 5.0 (up to 0.09 in intensity): the same preset generated under another
    version is other data, and figures measured on the two differ (a small flight's ATE went from
    3.3 to 6.1 %). The cache is kept, since it is consistent with itself and with every figure
    measured on it; deleting the folder regenerates it with the installed OpenCV. Caches from
    before this record (no ``opencv`` in ``summary.json``) are not checked.
    """
    import json
    import sys

    import cv2

    if folder in _noted:
        return
    try:
        made_with = json.loads((folder / "summary.json").read_text()).get("opencv")
    except (OSError, ValueError, AttributeError):
        return
    if made_with and made_with != cv2.__version__:
        _noted.add(folder)
        print(f"aerovis: note: {folder} was generated with OpenCV {made_with}, and OpenCV {cv2.__version__} is installed. "
              "Its text textures (cv2.putText) may render differently, so a regenerated preset would not be the "
              "same data. The cache is used as it is; delete the folder to regenerate it.", file=sys.stderr)
