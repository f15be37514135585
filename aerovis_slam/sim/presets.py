"""Named sets of sequences: ``train``, ``bench`` and ``tiny``.

A preset maps ``(seed, duration)`` to a list of :class:`SequenceSpec`; every sequence is a
pure function of its spec, so a preset with the same seed reproduces the same files.

* ``train``: 48 short (4 s) stereo sequences for learning, varied in scene (every sequence
  its own room), trajectory kind (cycled), speed, event-camera model, rig (DAVIS240-,
  Prophesee- and drone-like, all at 240x180-ish), HDR and lights-off segments. Revision 2 adds
  domain randomisation of the sensor and optics (:data:`TRAIN_SENSOR_RANGES`: photoreceptor
  bandwidth, dark shot noise, hot pixels, timestamp jitter, vignetting, posters from real photographs).
* ``bench``: a fixed evaluation set with every trajectory kind, named after its kind
  (``handheld_*``, ``shake_*``, ``spin_hdr_*``, ``drone8_*``, ``slider_*``);
  ``handheld_loop`` (and ``spin_hdr_window``, ``drone8_*``) return to their start;
  ``handheld_loop`` goes round its closed 10 s path and then on along its first 2 s, as a
  recording that walks past its starting point does, so that the revisit is seen while the camera
  still moves through texture (revision 2 of the preset; in revision 1 the path ended at its start,
  after a nearly event-free stretch that hid the revisit).
* ``tiny``: two 1 s sequences at 64x48 for tests and the notebook.

Example:
    >>> [s.name for s in preset_specs("tiny")]
    ['tiny_handheld', 'tiny_spin_hdr']
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..errors import DataError
from .events import EventConfig
from .scene import PHOTO_PREFIX, PHOTO_TEXTURES
from .simulator import SequenceSpec

PRESETS = ("train", "bench", "tiny")
#: A preset's revision: raised when its sequences change (the simulator itself unchanged), so that a
#: cache of the earlier sequences is not taken for the new ones (:func:`~aerovis_slam.sim.cache.preset_dir`).
PRESET_REVISIONS = {"train": 2, "bench": 2, "tiny": 1}


def _tiny(seed: int, duration: float | None) -> list[SequenceSpec]:
    d = duration or 1.0
    return [
        SequenceSpec("tiny_handheld", rig="tiny_stereo", scene_seed=seed, trajectory="handheld", trajectory_seed=seed,
                     speed=2.0, duration_s=d, frame_rate_hz=20, gt_rate_hz=200, noise_seed=seed),
        SequenceSpec("tiny_spin_hdr", rig="tiny_stereo", scene_seed=seed + 1, hdr=True, trajectory="spin",
                     trajectory_seed=seed + 1, duration_s=d, frame_rate_hz=20, gt_rate_hz=200, noise_seed=seed + 1),
    ]


def _bench(seed: int, duration: float | None) -> list[SequenceSpec]:
    def dur(x):
        return duration or x

    s = seed * 100
    return [
        # round a closed 10 s path, then its first 2 s again (loop_period_s scales with a --duration override)
        SequenceSpec("handheld_loop", rig="prophesee640_stereo", rig_scale=0.5, scene_seed=s + 1, trajectory="handheld",
                     trajectory_seed=s + 1, loop=True, loop_period_s=dur(12.0) * 10.0 / 12.0, duration_s=dur(12.0),
                     noise_seed=s + 1),
        SequenceSpec("handheld_office", rig="davis240_stereo", scene_seed=s + 2, trajectory="handheld",
                     trajectory_seed=s + 2, speed=1.5, duration_s=dur(8.0), noise_seed=s + 2),
        SequenceSpec("shake_rapid", rig="drone424", scene_seed=s + 3, trajectory="shake",
                     trajectory_seed=s + 3, duration_s=dur(4.0), noise_seed=s + 3),
        SequenceSpec("spin_hdr_window", rig="drone424", scene_seed=s + 4, hdr=True, trajectory="spin",
                     trajectory_seed=s + 4, duration_s=dur(8.0), noise_seed=s + 4),
        SequenceSpec("drone8_lit", rig="drone424", scene_seed=s + 5, trajectory="drone8",
                     trajectory_seed=s + 5, duration_s=dur(8.0), noise_seed=s + 5),
        SequenceSpec("drone8_lightsoff", rig="drone424", scene_seed=s + 6, trajectory="drone8",
                     trajectory_seed=s + 6, duration_s=dur(8.0), lights_off=[(0.4 * dur(8.0), 0.7 * dur(8.0))], noise_seed=s + 6),
        SequenceSpec("slider_wall", rig="davis240_stereo", scene_seed=s + 7, trajectory="slider",
                     trajectory_seed=s + 7, duration_s=dur(4.0), noise_seed=s + 7),
    ]


# (rig, scale): all close to 240x180 pixels (see the module docstring for why).
_TRAIN_RIGS = (("davis240_stereo", 1.0), ("prophesee640_stereo", 0.375), ("drone424", 0.75))
# Cycled (not drawn) so that every kind is represented: handheld twice per cycle of six.
_TRAIN_KINDS = ("handheld", "shake", "spin", "drone8", "slider", "handheld")
_TRAIN_SPEED = {"shake": (0.4, 0.6), "spin": (0.6, 1.0)}


def _train(seed: int, duration: float | None, n: int = 48) -> list[SequenceSpec]:
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x7EA1]))
    d = duration or 4.0
    specs = []
    for i in range(n):
        rig, scale = _TRAIN_RIGS[(i // len(_TRAIN_KINDS)) % len(_TRAIN_RIGS)]
        kind = _TRAIN_KINDS[i % len(_TRAIN_KINDS)]
        hdr = bool(rng.random() < 0.2)
        lights = []
        if rng.random() < 0.1 and d > 2.0:
            a = float(rng.uniform(0.5, d - 1.5))
            lights = [(a, a + float(rng.uniform(0.5, 1.0)))]
        ev = EventConfig(threshold=float(rng.uniform(0.15, 0.35)), threshold_sigma=float(rng.uniform(0.01, 0.05)),
                         refractory_us=int(rng.choice([0, 100, 500])), leak_hz=float(rng.uniform(0.0, 0.3)),
                         shot_noise_hz=float(rng.uniform(0.0, 0.5)))
        sensor, optics = _sensor_randomisation(np.random.default_rng(np.random.SeedSequence([seed, 0x5E45, i])))
        specs.append(SequenceSpec(
            f"train_{i:03d}_{kind}", rig=rig, rig_scale=scale, scene_seed=seed * 100003 + 1000 + i, hdr=hdr,
            lights_off=lights, trajectory=kind, trajectory_seed=seed * 100003 + 2000 + i,
            # Shakes and spins sweep the whole image quickly (many render steps, many events):
            # milder speeds there keep the preset near ten minutes on two cores.
            speed=float(rng.uniform(*_TRAIN_SPEED.get(kind, (0.7, 1.5)))),
            duration_s=d, frame_rate_hz=20, gt_rate_hz=200, events=dataclasses.replace(ev, **sensor), **optics,
            noise_seed=seed * 100003 + 3000 + i))
    return specs


#: Domain randomisation of the ``train`` preset's sensors and optics (revision 2), per sequence: each
#: effect of :class:`~aerovis_slam.sim.events.EventConfig` and the lens is present in a share of the
#: sequences, at a level drawn from a range around what real sensors show (``aerovis-data stats`` on
#: real recordings, docs/real-data.md): (share of sequences, low, high), log-uniform where the range spans
#: decades. ``bench`` keeps every effect off, so its figures stay comparable.
TRAIN_SENSOR_RANGES = {
    "cutoff_hz": (0.5, 50.0, 2000.0),               # photoreceptor bandwidth at full intensity, log-uniform
    "shot_noise_dark_factor": (0.5, 2.0, 10.0),     # dark pixels' shot noise over bright ones'
    "hot_pixel_fraction": (0.5, 1e-5, 3e-3),        # log-uniform; Prophesee Gen3 recordings show ~3e-3, a DAVIS346 ~5e-5
    "hot_pixel_hz": (1.0, 5.0, 300.0),              # log-uniform (where there are hot pixels)
    "timestamp_jitter_us": (0.5, 10.0, 300.0),      # log-uniform
    "off_threshold_ratio": (0.8, 0.45, 1.0),        # real recordings of moving scenes: 36-37 % ON events, a ratio ~0.56
    "vignetting": (0.5, 0.2, 1.0),                  # strength of the cos^4 fall-off
    "photos": (0.5, 2, len(PHOTO_TEXTURES)),        # posters from real photographs: how many of them
}
_LOG_UNIFORM = {"cutoff_hz", "hot_pixel_fraction", "hot_pixel_hz", "timestamp_jitter_us"}


def _sensor_randomisation(rng: np.random.Generator) -> tuple[dict, dict]:
    """(EventConfig fields, SequenceSpec fields) of one ``train`` sequence, drawn from :data:`TRAIN_SENSOR_RANGES`
    by a generator of its own (so the preset's other draws are those of revision 1)."""
    sensor, optics = {}, {}
    for key, (share, lo, hi) in TRAIN_SENSOR_RANGES.items():
        present = rng.random() < share
        value = float(np.exp(rng.uniform(np.log(lo), np.log(hi)))) if key in _LOG_UNIFORM else float(rng.uniform(lo, hi))
        if not present:
            continue
        if key == "vignetting":
            optics["vignetting"] = value
        elif key == "photos":
            names = rng.permutation(PHOTO_TEXTURES)[: int(round(value))]
            optics["user_textures"] = [PHOTO_PREFIX + str(n) for n in names]
        else:
            sensor[key] = value
    return sensor, optics


def preset_specs(name: str, seed: int = 0, duration: float | None = None) -> list[SequenceSpec]:
    """The sequences of a preset.

    Args:
        name: one of :data:`PRESETS`.
        seed: preset seed (all sequence seeds derive from it).
        duration: override every sequence's duration (seconds).

    Raises:
        DataError: for an unknown preset.
    """
    if name not in PRESETS:
        raise DataError(None, f"unknown preset {name!r}; expected one of {list(PRESETS)}")
    if duration is not None and duration <= 0:
        raise DataError(None, f"--duration must be positive, got {duration}")
    specs = {"train": _train, "bench": _bench, "tiny": _tiny}[name](int(seed), duration)
    return [dataclasses.replace(s) for s in specs]
