"""A decoded, memory-mapped copy of the sequences a training run reads (``data.event_cache``).

The canonical files keep events, frames and depth compressed in 64k-event chunks (small on disk,
fast to stream once). A training pair reads two short windows at random places of random
sequences: about half of a loader worker's time went into h5py decompressing chunks for ~80k events
per view (measured with gzip-compressed events: 23.6 ms per pair on this box, 45 % of it in HDF5
reads; the events are Blosc-LZ4 now, which decodes ~3.5x faster), and on a GPU the loader
is the bottleneck. Here each sequence's event arrays, frames and depth maps are written once as
plain ``.npy`` files and memory-mapped, so every worker reads them through the shared page cache.
No library does this for HDF5 (h5py's chunk cache is per process and per dataset, and did not help:
21.1 against 22.4 ms per pair with 16 MB of it), hence the few lines here.

Layout: ``<cache_dir>/<key>/<cam>_{t,x,y,p,frames,depth}.npy`` with ``key`` from the file's resolved
path, size and modification time, so a regenerated sequence gets a fresh copy. A copy is built in a
temporary folder and renamed into place: concurrent loader workers that build the same copy end with
one complete folder, and an interrupted build leaves nothing that looks finished (the build folder of a
killed run is deleted by the next :func:`prepare_decoded` of that sequence). Copies of files that
changed since are not removed: delete the cache folder to reclaim the space.
"""

from __future__ import annotations

import hashlib
import os
import shutil
from pathlib import Path

import numpy as np

from aerovis_slam.events import EventArray
from aerovis_slam.fileio import make_build_dir, remove_abandoned
from aerovis_slam.io.sequence import Sequence


def cache_key(path: str | os.PathLike) -> str:
    """Folder name of a sequence's decoded copy: a hash of its resolved path, size and mtime."""
    p = Path(path).resolve()
    st = p.stat()
    return hashlib.sha1(f"{p}|{st.st_size}|{st.st_mtime_ns}".encode()).hexdigest()[:20]


def build_decoded(seq: Sequence, folder: Path) -> Path:
    """Write the decoded copy of ``seq`` into ``folder`` (atomically; returns ``folder``)."""
    if folder.is_dir():
        return folder
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = make_build_dir(folder)
    try:
        for cam in seq.cameras:
            ev = seq.events(cam)
            for name in ("t", "x", "y", "p"):
                np.save(tmp / f"{cam}_{name}.npy", np.ascontiguousarray(getattr(ev, name)))
            for kind in ("frames", "depth"):
                times = seq.frame_times(cam, kind)
                if times is not None:
                    np.save(tmp / f"{cam}_{kind}.npy", np.stack([seq.frame(cam, i, kind) for i in range(len(times))]))
        try:
            os.rename(tmp, folder)
        except OSError:
            if not folder.is_dir():  # not a concurrent builder that finished first: a real error
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return folder


def prepare_decoded(paths: list[str | os.PathLike], cache_dir: str | os.PathLike, *, progress: bool = True) -> None:
    """Build the missing decoded copies of ``paths`` now (with a progress bar), so that loader
    workers only map them and never stall a training step decoding (nor decode the same file twice)."""
    from tqdm import tqdm

    folders = {Path(p): Path(cache_dir) / cache_key(p) for p in paths}
    for folder in folders.values():
        remove_abandoned(folder)
    todo = [(path, folder) for path, folder in folders.items() if not folder.is_dir()]
    for path, folder in tqdm(todo, desc="decoding sequences (data.event_cache)", unit="seq", disable=not progress or not todo):
        with Sequence(path) as seq:
            build_decoded(seq, folder)


class DecodedSequence:
    """The reads of a training pair (:func:`aerovis_train.data.compute_mcts`, frames, depth) served
    from the memory-mapped decoded copy of ``seq``; anything else goes to ``seq`` itself.

    Same results as the :class:`~aerovis_slam.io.sequence.Sequence` methods it replaces.
    """

    def __init__(self, seq: Sequence, cache_dir: str | os.PathLike):
        self._seq = seq
        self.folder = build_decoded(seq, Path(cache_dir) / cache_key(seq.path))
        self._arrays: dict[str, np.ndarray] = {}

    def _array(self, name: str) -> np.ndarray | None:
        if name not in self._arrays:
            f = self.folder / f"{name}.npy"
            self._arrays[name] = np.load(f, mmap_mode="r") if f.is_file() else None
        return self._arrays[name]

    def __getattr__(self, name):  # everything not overridden: the sequence's own
        if name.startswith("_"):  # never recurse before __init__ ran (e.g. while unpickling)
            raise AttributeError(name)
        return getattr(self._seq, name)

    def index_at(self, cam: str, t_us: int) -> int:
        """Index of the first event with ``t >= t_us`` (as ``Sequence.index_at``)."""
        t = self._array(f"{cam}_t")
        return 0 if t is None else int(np.searchsorted(t, t_us, side="left"))

    def events_by_index(self, cam: str, start: int, stop: int) -> EventArray:
        t = self._array(f"{cam}_t")
        if t is None:
            return EventArray.empty()
        sl = slice(max(start, 0), max(stop, 0))
        return EventArray(*(np.array(self._array(f"{cam}_{n}")[sl]) for n in ("t", "x", "y", "p")))

    def frame(self, cam: str, index: int, kind: str = "frames") -> np.ndarray:
        a = self._array(f"{cam}_{kind}")
        return self._seq.frame(cam, index, kind) if a is None else np.array(a[index])
