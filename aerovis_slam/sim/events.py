"""ESIM-style event generation with v2e-style sensor noise.

Each pixel keeps a reference log intensity ``ref``. Between two renders ``(t0, L0)`` and
``(t1, L1)`` of the log intensity ``L = log(I + eps)`` it emits one event per threshold
crossing: ON at levels ``ref + k C+`` while ``L1 >= ref + k C+``, OFF at ``ref - k C-`` while
``L1 <= ref - k C-``, each timestamped by linear interpolation
``t = t0 + (level - L0) / (L1 - L0) (t1 - t0)``. The reference moves by one threshold per
crossing, even when the refractory period suppresses the event (a pixel that fired less than
``refractory_us`` ago stays silent, as a real DVS pixel resetting).

Realism (v2e): per-pixel thresholds drawn once, ``C+/- ~ N(C, sigma)`` clipped to
``[threshold_min, inf)``; leak events (the reference drifts down by ``leak_hz * C+`` per second
with 10 % per-pixel spread, so an unlit static pixel emits ON events at ~``leak_hz``); and
shot-noise events (Poisson, ``shot_noise_hz`` per pixel, random polarity). Noise events obey
the refractory period too, but do not move the reference. Optional, each off by default (so a
sequence without them is bit-identical to one made before they existed):

* photoreceptor bandwidth (v2e's intensity-dependent low-pass): the log intensity the pixel sees
  follows the scene's through a first-order filter of cut-off ``cutoff_hz * (I + 0.1) / 1.1`` (``I``
  the linear intensity, 1 = the brightest diffuse white), so dark pixels lag and smear;
* shot noise that rises in the dark: a pixel's rate is ``shot_noise_hz * (1 + (dark - 1)(1 - I))``
  with ``dark = shot_noise_dark_factor`` (photon noise weighs more at low light);
* hot pixels: a ``hot_pixel_fraction`` of the pixels fires at about ``hot_pixel_hz`` (0.5-2x, one
  polarity each), whatever the scene;
* timestamp jitter: signal events' times get Gaussian noise of ``timestamp_jitter_us``, kept inside
  their render step so that the stream stays sorted;
* ON/OFF asymmetry: OFF thresholds ``off_threshold_ratio`` times the ON ones.

Vectorised in numba passes: per-pixel crossing counts (whose running sum gives each pixel's
output offset), then every crossing's timestamp, pixel by pixel; a merge with the (few) noise
events applies the refractory period per pixel in one sequential pass. Events of one step are
then sorted by time, so a stream of steps stays sorted.

Example:
    >>> gen = EventGenerator(2, 1, EventConfig(threshold_sigma=0.0, noise=False, refractory_us=0), np.random.default_rng(0))
    >>> gen.reset(np.array([[0.0, 0.0]]), 0)
    >>> ev = gen.step(np.array([[0.5, -0.3]]), 1000)
    >>> ev.t.tolist(), ev.x.tolist(), ev.p.tolist()
    ([400, 667, 800], [0, 1, 0], [1, 0, 1])
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

from ..events import EventArray


@dataclass
class EventConfig:
    """Parameters of the event camera model.

    Attributes:
        threshold: mean contrast threshold ``C`` (log-intensity units) of both polarities.
        threshold_sigma: per-pixel standard deviation of the thresholds (mismatch).
        threshold_min: lower clip of the thresholds.
        refractory_us: per-pixel dead time after an emitted event (µs); 0 disables.
        noise: master switch for leak and shot noise.
        leak_hz: leak-event rate per pixel (Hz).
        shot_noise_hz: shot-noise rate per pixel (Hz).
        eps: offset in ``L = log(I + eps)`` (relative radiance units; sets the dark floor).
        cutoff_hz: photoreceptor cut-off frequency at full intensity (Hz); 0: unlimited bandwidth.
        shot_noise_dark_factor: shot-noise rate in the dark over that at full intensity (1: uniform).
        hot_pixel_fraction: share of pixels that fire regardless of the scene (0: none).
        hot_pixel_hz: mean rate of a hot pixel (Hz).
        timestamp_jitter_us: standard deviation of the signal events' time noise (µs); 0: exact.
        off_threshold_ratio: OFF threshold over ON threshold (mean and spread); real sensors with an OFF
            threshold about half the ON one emit about a third of their events as ON (1: symmetric).
    """

    threshold: float = 0.2
    threshold_sigma: float = 0.03
    threshold_min: float = 0.05
    refractory_us: int = 100
    noise: bool = True
    leak_hz: float = 0.1
    shot_noise_hz: float = 0.1
    eps: float = 1e-3
    cutoff_hz: float = 0.0
    shot_noise_dark_factor: float = 1.0
    hot_pixel_fraction: float = 0.0
    hot_pixel_hz: float = 20.0
    timestamp_jitter_us: float = 0.0
    off_threshold_ratio: float = 1.0

    def __post_init__(self) -> None:
        if self.threshold <= 0 or self.threshold_min <= 0:
            raise ValueError(f"thresholds must be positive (threshold={self.threshold}, threshold_min={self.threshold_min})")
        for name in ("threshold_sigma", "refractory_us", "leak_hz", "shot_noise_hz", "cutoff_hz", "hot_pixel_hz", "timestamp_jitter_us"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"EventConfig.{name} must be a finite number >= 0, got {v}")
        if not (np.isfinite(self.off_threshold_ratio) and self.off_threshold_ratio > 0):
            raise ValueError(f"EventConfig.off_threshold_ratio must be positive, got {self.off_threshold_ratio}")
        if not (np.isfinite(self.shot_noise_dark_factor) and self.shot_noise_dark_factor > 0):
            raise ValueError(f"EventConfig.shot_noise_dark_factor must be positive, got {self.shot_noise_dark_factor}")
        if not 0.0 <= self.hot_pixel_fraction <= 1.0:
            raise ValueError(f"EventConfig.hot_pixel_fraction must be in [0, 1], got {self.hot_pixel_fraction}")


def log_intensity(radiance: np.ndarray, eps: float) -> np.ndarray:
    """``L = log(I + eps)`` as float64 (H, W) (float64 keeps crossing levels exact over long runs)."""
    return np.log(np.asarray(radiance, np.float64) + eps)


@nb.njit(cache=True)
def _count_crossings(L1, ref, cpos, cneg, counts):  # pragma: no cover - compiled
    n = L1.size
    total = 0
    for i in range(n):
        d = L1[i] - ref[i]
        if d >= cpos[i]:
            k = int(np.floor(d / cpos[i]))
        elif -d >= cneg[i]:
            k = int(np.floor(-d / cneg[i]))
        else:
            k = 0
        counts[i] = k
        total += k
    return total


@nb.njit(cache=True)
def _fill_crossings(L0, L1, ref, cpos, cneg, counts, t0, t1, out_pix, out_t, out_p):  # pragma: no cover
    """Timestamps of all crossings; pixels in index order, times increasing within a pixel."""
    n = L1.size
    j = 0
    dt = float(t1 - t0)
    for i in range(n):
        k = counts[i]
        if k == 0:
            continue
        dl = L1[i] - L0[i]
        up = L1[i] > ref[i]
        c = cpos[i] if up else -cneg[i]
        r = ref[i]
        for m in range(k):
            r += c
            if dl != 0.0:
                tf = t0 + (r - L0[i]) / dl * dt
            else:
                tf = float(t1)  # the reference drifted (leak) while the intensity held still
            # Leak can move the reference so that a level lies just outside [L0, L1]: clamp.
            if tf < t0:
                tf = float(t0)
            elif tf > t1:
                tf = float(t1)
            out_pix[j] = i
            out_t[j] = int(np.floor(tf + 0.5))
            out_p[j] = 1 if up else 0
            j += 1
        ref[i] = r


@nb.njit(cache=True)
def _merge_refractory(sp, st, spol, npix, nt, npol, last_t, refractory, op, ot, opol):  # pragma: no cover
    """Merge signal and noise events (each grouped by pixel, time-ordered within) and apply the
    per-pixel dead time sequentially; writes the survivors to ``op, ot, opol``, returns their number."""
    i = j = n = 0
    ns, nn = sp.size, npix.size
    while i < ns or j < nn:
        if j >= nn or (i < ns and (sp[i] < npix[j] or (sp[i] == npix[j] and st[i] <= nt[j]))):
            pix, t, pol = sp[i], st[i], spol[i]
            i += 1
        else:
            pix, t, pol = npix[j], nt[j], npol[j]
            j += 1
        if refractory > 0:
            if t - last_t[pix] < refractory:
                continue
            last_t[pix] = t
        op[n], ot[n], opol[n] = pix, t, pol
        n += 1
    return n


class EventGenerator:
    """Event camera of one sensor, stepping through successive log-intensity renders.

    Args:
        width, height: sensor size in pixels.
        config: the camera model.
        rng: draws the per-pixel thresholds and leak rates once, then the shot noise.

    Attributes:
        c_pos, c_neg: float64 (H, W) per-pixel thresholds.
        ref: float64 (H, W) per-pixel reference log intensity.
    """

    def __init__(self, width: int, height: int, config: EventConfig, rng: np.random.Generator):
        self.width, self.height, self.config, self.rng = int(width), int(height), config, rng
        shape = (self.height, self.width)
        c = config
        self.c_pos = np.maximum(rng.normal(c.threshold, c.threshold_sigma, shape), c.threshold_min) if c.threshold_sigma > 0 else np.full(shape, c.threshold)
        c_off, sigma_off = c.threshold * c.off_threshold_ratio, c.threshold_sigma * c.off_threshold_ratio
        self.c_neg = np.maximum(rng.normal(c_off, sigma_off, shape), c.threshold_min) if c.threshold_sigma > 0 else np.full(shape, c_off)
        self.leak_per_s = (c.leak_hz * self.c_pos * np.maximum(rng.normal(1.0, 0.1, shape), 0.0)).ravel() if (c.noise and c.leak_hz > 0) else None
        self.ref = np.zeros(shape)
        self._L = np.zeros(shape)
        self._t = 0
        self._last_t = np.full(self.width * self.height, np.iinfo(np.int64).min // 2, np.int64)
        self._counts = np.zeros(self.width * self.height, np.int64)
        # drawn after everything above, and only when enabled, so that sequences without hot pixels keep
        # their random streams (and so their events) unchanged
        self.hot_pix = np.empty(0, np.int64)
        if c.noise and c.hot_pixel_fraction > 0:
            self.hot_pix = np.flatnonzero(rng.random(self.width * self.height) < c.hot_pixel_fraction)
            self.hot_rate_hz = c.hot_pixel_hz * rng.uniform(0.5, 2.0, len(self.hot_pix))
            self.hot_pol = rng.integers(0, 2, len(self.hot_pix)).astype(np.int8)

    def reset(self, log_image: np.ndarray, t_us: int) -> None:
        """Start at ``t_us`` with the references at the current log intensity (H, W)."""
        L = np.asarray(log_image, np.float64)
        if L.shape != (self.height, self.width):
            raise ValueError(f"log image has shape {L.shape}, expected {(self.height, self.width)}")
        self.ref = L.copy()
        self._L = L.copy()
        self._t = int(t_us)

    def step(self, log_image: np.ndarray, t_us: int) -> EventArray:
        """Advance to a new render (H, W) at ``t_us`` and return the events of ``(t_prev, t_us]``, sorted."""
        L1 = np.ascontiguousarray(log_image, np.float64)
        if L1.shape != (self.height, self.width):
            raise ValueError(f"log image has shape {L1.shape}, expected {(self.height, self.width)}")
        t0, t1 = self._t, int(t_us)
        if t1 < t0:
            raise ValueError(f"time goes backwards: {t1} µs after {t0} µs")
        c = self.config
        dt_s = (t1 - t0) * 1e-6
        if c.cutoff_hz > 0 and t1 > t0:
            # exact response of the first-order low-pass over the step to the new render (a step input)
            bandwidth = c.cutoff_hz * (self._intensity(L1) + 0.1) / 1.1
            L1 = self._L + (1.0 - np.exp(-2.0 * np.pi * bandwidth * dt_s)) * (L1 - self._L)
        ref = self.ref.ravel()
        if self.leak_per_s is not None:
            ref -= self.leak_per_s * dt_s
        L0f, L1f = self._L.ravel(), L1.ravel()
        n = _count_crossings(L1f, ref, self.c_pos.ravel(), self.c_neg.ravel(), self._counts)
        pix = np.empty(n, np.int64)
        t = np.empty(n, np.int64)
        p = np.empty(n, np.int8)
        if n:
            _fill_crossings(L0f, L1f, ref, self.c_pos.ravel(), self.c_neg.ravel(), self._counts, t0, t1, pix, t, p)
            if c.timestamp_jitter_us > 0:
                t = np.clip(t + np.rint(self.rng.normal(0.0, c.timestamp_jitter_us, n)).astype(np.int64), t0 + 1, t1)
                order = np.lexsort((t, pix))  # the refractory merge wants each pixel's events in time order
                pix, t, p = pix[order], t[order], p[order]
        npix, nt, npol = self._noise_events(L1f, t0, t1)
        m = len(npix)
        if m or c.refractory_us > 0:
            k = n + m
            op, ot, opol = np.empty(k, np.int64), np.empty(k, np.int64), np.empty(k, np.int8)
            k = _merge_refractory(pix, t, p, npix, nt, npol, self._last_t, int(c.refractory_us), op, ot, opol)
            pix, t, p = op[:k], ot[:k], opol[:k]
        self._L = L1.copy()
        self._t = t1
        order = np.argsort(t, kind="stable")
        pix, t, p = pix[order], t[order], p[order]
        return EventArray(t, pix % self.width, pix // self.width, p)

    def _intensity(self, L: np.ndarray) -> np.ndarray:
        """Linear intensity of log intensities ``L``, clipped to [0, 1] (1: the brightest diffuse white)."""
        return np.clip(np.exp(L) - self.config.eps, 0.0, 1.0)

    def _noise_events(self, L1f: np.ndarray, t0: int, t1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Shot-noise and hot-pixel events of ``(t0, t1]``: (pixel, t, polarity), grouped by pixel, time-ordered within."""
        c = self.config
        none = np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0, np.int8)
        if not c.noise or t1 <= t0:
            return none
        dt_s = (t1 - t0) * 1e-6
        parts = []
        if c.shot_noise_hz > 0:
            if c.shot_noise_dark_factor == 1.0:
                m = self.rng.poisson(c.shot_noise_hz * L1f.size * dt_s)
                if m:
                    parts.append((self.rng.integers(0, L1f.size, m), self.rng.integers(t0 + 1, t1 + 1, m),
                                  self.rng.integers(0, 2, m).astype(np.int8)))
            else:
                rate = c.shot_noise_hz * (1.0 + (c.shot_noise_dark_factor - 1.0) * (1.0 - self._intensity(L1f)))
                cum = np.cumsum(rate)
                m = self.rng.poisson(cum[-1] * dt_s)
                if m:  # each noise event at a pixel drawn in proportion to its rate
                    npix = np.minimum(np.searchsorted(cum, self.rng.random(m) * cum[-1], side="right"), L1f.size - 1)
                    parts.append((npix, self.rng.integers(t0 + 1, t1 + 1, m), self.rng.integers(0, 2, m).astype(np.int8)))
        if len(self.hot_pix):
            k = self.rng.poisson(self.hot_rate_hz * dt_s)
            if k.any():
                parts.append((np.repeat(self.hot_pix, k), self.rng.integers(t0 + 1, t1 + 1, int(k.sum())), np.repeat(self.hot_pol, k)))
        if not parts:
            return none
        npix, nt, npol = (np.concatenate(x) for x in zip(*parts))
        order = np.lexsort((nt, npix))  # group by pixel, time-ordered within
        return npix[order], nt[order], npol[order]


def video_to_events(
    images: np.ndarray,
    t_us: np.ndarray,
    config: EventConfig | None = None,
    *,
    seed: int = 0,
    gamma: float = 2.2,
) -> EventArray:
    """Events from a video: the log intensity is interpolated linearly between frames.

    The generator's timestamps already interpolate linearly between two renders, so each
    frame interval is one exact step of the same ESIM model (no sub-steps needed). Frames
    are assumed gamma-encoded; they are linearised with ``(x / 255) ** gamma``.

    Args:
        images: uint8 (N, H, W) grayscale frames (or float in [0, 1], taken as linear).
        t_us: (N,) int64 strictly increasing frame timestamps in µs.
        config: camera model (defaults to :class:`EventConfig`).
        seed: seeds thresholds and noise.
        gamma: display gamma of uint8 frames.

    Returns:
        All events, sorted by time.
    """
    config = config or EventConfig()
    images = np.asarray(images)
    t_us = np.asarray(t_us, np.int64)
    if images.ndim != 3 or len(images) != len(t_us) or len(t_us) < 2:
        raise ValueError(f"need (N, H, W) frames with N >= 2 matching N timestamps, got {images.shape} and {t_us.shape}")
    if np.any(np.diff(t_us) <= 0):
        raise ValueError("frame timestamps must be strictly increasing")

    def linear(img):
        return (img.astype(np.float64) / 255.0) ** gamma if img.dtype == np.uint8 else img.astype(np.float64)

    gen = EventGenerator(images.shape[2], images.shape[1], config, np.random.default_rng(seed))
    gen.reset(log_intensity(linear(images[0]), config.eps), int(t_us[0]))
    chunks = [gen.step(log_intensity(linear(img), config.eps), int(t)) for img, t in zip(images[1:], t_us[1:])]
    return EventArray.concatenate(chunks)
