"""The software a result was measured with: recorded next to every benchmark and run.

A SLAM run is deterministic within one environment, but a new resolution of its libraries (numpy,
OpenCV, ONNX Runtime, gtsam, numba, ...) moves the figures: on the `bench` preset the same commit
gave 2.51 % and 3.14 % sync ATE on handheld_loop in two environments. Results from different
sessions are only comparable when each says what it ran on, so ``metrics.json`` of a run, the
``environment.json`` of a bench and ``metrics.json`` / ``compare.json`` of training and evaluation
all carry :func:`software_versions`. :func:`blas_thread_limit` sets what it records of the BLAS
libraries for the length of a SLAM run.
"""

from __future__ import annotations

import contextlib
import functools
import platform
import subprocess
from importlib import metadata
from pathlib import Path

from . import __version__

#: distributions whose version moves the runtime's figures (the runtime's own dependencies)
RUNTIME_DISTRIBUTIONS = ("numpy", "opencv-python-headless", "opencv-python", "onnxruntime", "onnxruntime-gpu", "gtsam", "scipy",
                         "numba", "evo", "h5py", "hdf5plugin")
#: distributions that move training and evaluation figures on top of those
TRAINING_DISTRIBUTIONS = ("torch", "lightning", "kornia", "onnx", "hydra-core", "torchao")


def _distribution_version(name: str) -> str | None:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


@functools.lru_cache(maxsize=1)
def _source_commit() -> tuple[str | None, bool | None]:
    """(git commit, has uncommitted changes) of the checkout this package runs from, or (None, None)
    for an installed wheel, a machine without git, or anything else that does not answer in 5 s."""
    root = Path(__file__).resolve().parent.parent
    if not (root / ".git").exists():
        return None, None
    try:
        sha = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5, check=True)
        status = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                                text=True, timeout=5, check=True)
    except (OSError, subprocess.SubprocessError):
        return None, None
    return sha.stdout.strip() or None, bool(status.stdout.strip())


def software_versions(*, training: bool = False) -> dict:
    """What the figures of this process were measured with.

    Args:
        training: add the training stack (torch, lightning, ...) to the runtime's distributions.

    Returns:
        ``{"python": "3.11.9", "platform": "Linux-...-x86_64", "aerovis": "0.1.0", "commit": sha or None,
        "uncommitted_changes": bool or None, "packages": {distribution: version}, "host": host_description(),
        "blas": blas_libraries() less num_threads}``, with only the installed distributions in ``packages``
        (JSON-ready).
    """
    names = RUNTIME_DISTRIBUTIONS + (TRAINING_DISTRIBUTIONS if training else ())
    packages = {n: v for n in names if (v := _distribution_version(n)) is not None}
    commit, dirty = _source_commit()
    return {"python": platform.python_version(), "platform": platform.platform(), "aerovis": __version__,
            "commit": commit, "uncommitted_changes": dirty, "packages": packages, "host": host_description(),
            # without num_threads: a run holds it at SlamConfig.blas_threads, whatever it is when recorded
            "blas": [{k: v for k, v in b.items() if k != "num_threads"} for b in blas_libraries()]}


def blas_libraries() -> list[dict]:
    """The BLAS libraries numpy (and whatever else is loaded) calls, as threadpoolctl finds them:
    ``[{"library": "openblas", "version": "0.3.31...", "architecture": "SkylakeX", "threading_layer":
    "pthreads", "num_threads": 2}]``.

    OpenBLAS picks its kernels by CPU at load time (``architecture``), one more reason figures move
    between machines; ``num_threads`` is the setting at the time of the call (a SLAM run holds it at
    ``SlamConfig.blas_threads``, see :func:`blas_thread_limit`).
    """
    import numpy  # noqa: F401  (loads the BLAS that threadpoolctl then finds)
    from threadpoolctl import threadpool_info

    found = [{"library": i.get("internal_api"), "version": i.get("version"), "architecture": i.get("architecture"),
              "threading_layer": i.get("threading_layer"), "num_threads": i.get("num_threads")}
             for i in threadpool_info() if i.get("user_api") == "blas"]
    return sorted(found, key=lambda b: (str(b["library"]), str(b["version"])))  # load order varies between runs


def blas_thread_limit(threads: int | None):
    """Context manager: every loaded BLAS runs ``threads`` threads inside it (None: unchanged).

    See ``SlamConfig.blas_threads`` for why the SLAM runtime uses one. threadpoolctl sets the limit
    through the loaded BLAS library's own API (``openblas_set_num_threads``), which an environment
    variable cannot do once numpy is imported.
    """
    if threads is None:
        return contextlib.nullcontext()
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=int(threads), user_api="blas")


#: SIMD levels, widest first: the first one /proc/cpuinfo lists is recorded
_SIMD_LEVELS = ("avx512f", "avx2", "avx", "sse4_2", "neon", "asimd")


def _cpuinfo(path: str = "/proc/cpuinfo") -> tuple[str | None, str | None]:
    """(CPU model name, widest SIMD level) from Linux's cpuinfo, or (None, None) elsewhere."""
    try:
        text = Path(path).read_text(errors="replace")
    except OSError:
        return None, None
    model, flags = None, set()
    for line in text.splitlines():
        key, _, value = line.partition(":")
        key = key.strip().lower()
        if model is None and key in ("model name", "hardware", "cpu model"):
            model = value.strip() or None
        elif not flags and key in ("flags", "features"):
            flags = set(value.split())
    return model, next((level for level in _SIMD_LEVELS if level in flags), None)


def host_description() -> dict:
    """The machine figures were measured on: ``{"machine": "x86_64", "processor": str or None,
    "cpu_model": str or None, "simd": "avx512f" | "avx2" | ... or None, "cpus": int}``.

    Latencies depend on it, and so do sync SLAM runs: with the same library versions, two machines
    gave different ATE on four bench sequences of seven (docs/slam.md, "The full bench at 3eb9c48"),
    as vectorised kernels round differently."""
    import os

    model, simd = _cpuinfo()
    return {"machine": platform.machine(), "processor": platform.processor() or None, "cpu_model": model, "simd": simd,
            "cpus": os.cpu_count()}


def describe(versions: dict) -> str:
    """One line for a table's footer: ``aerovis 0.1.0 (08f0e21), python 3.11.9, numpy 2.4.6, ..., openblas 0.3.31
    (SkylakeX); on CPU (avx2, 2 cpus)``."""
    commit = versions.get("commit")
    head = f"aerovis {versions.get('aerovis')}" + (f" ({commit[:7]}{'+changes' if versions.get('uncommitted_changes') else ''})"
                                                   if commit else "")
    line = ", ".join([head, f"python {versions.get('python')}"] + [f"{k} {v}" for k, v in versions.get("packages", {}).items()]
                     + [f"{b.get('library')} {b.get('version')}" + (f" ({b['architecture']})" if b.get("architecture") else "")
                        for b in versions.get("blas", [])])
    host = versions.get("host") or {}
    if host.get("cpu_model") or host.get("simd"):
        details = ", ".join(str(x) for x in (host.get("simd"), f"{host.get('cpus')} cpus" if host.get("cpus") else None) if x)
        line += f"; on {host.get('cpu_model') or host.get('machine')}" + (f" ({details})" if details else "")
    return line
