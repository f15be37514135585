"""IMU measurements from a trajectory's analytic derivatives.

``gyro = omega_body + b_g + n_g`` and ``acc = R_world_body^T (a_world - g_world) + b_a + n_a`` with
``g_world = (0, 0, -9.81)`` m/s² (z up), so a resting IMU reads ``+9.81`` on its up axis.
Noise follows Kalibr's discrete model: white noise ``sigma_d = density * sqrt(rate)`` per
sample and a bias random walk ``b_{k+1} = b_k + random_walk * sqrt(dt) * N(0, I)``.

Example:
    >>> import numpy as np
    >>> from aerovis_slam.sim.trajectory import make_trajectory
    >>> traj = make_trajectory("static", np.random.default_rng(0), 1.0, -np.ones(3), np.ones(3))
    >>> imu = simulate_imu(traj, 200.0, noise=None)
    >>> len(imu), round(float(np.linalg.norm(imu.acc[0])), 2)
    (201, 9.81)
"""

from __future__ import annotations

import numpy as np

from ..calib import ImuNoise
from ..measurements import ImuSamples
from .trajectory import GRAVITY, Trajectory

G_WORLD = np.array([0.0, 0.0, -GRAVITY])


def imu_times_us(duration_s: float, rate_hz: float) -> np.ndarray:
    """Sample times ``0, 1/rate, ...`` up to ``duration_s`` inclusive, int64 µs (rounded)."""
    n = int(np.floor(duration_s * rate_hz + 1e-9)) + 1
    return np.round(np.arange(n) * (1e6 / rate_hz)).astype(np.int64)


def simulate_imu(traj: Trajectory, rate_hz: float, noise: ImuNoise | None,
                 rng: np.random.Generator | None = None, *, initial_bias: bool = False) -> ImuSamples:
    """Sample gyro and accelerometer at ``rate_hz`` over the trajectory.

    Args:
        traj: body trajectory (``T_world_body``; the body is the IMU frame).
        rate_hz: sampling rate in Hz.
        noise: continuous-time densities, or ``None`` for exact measurements.
        rng: generator for the noise (required with ``noise``).
        initial_bias: start the biases at a random turn-on value (0.02 m/s², 0.002 rad/s
            per axis, 1 sigma) instead of zero.

    Returns:
        :class:`ImuSamples` with ``t`` (N,) µs, ``gyro`` (N, 3) rad/s, ``acc`` (N, 3) m/s².
    """
    t_us = imu_times_us(traj.duration_s, rate_hz)
    t = t_us * 1e-6
    R = traj.rotation(t)
    gyro = traj.angular_velocity(t)
    acc = np.einsum("nji,nj->ni", R, traj.position(t, 2) - G_WORLD)
    if noise is not None:
        if rng is None:
            raise ValueError("simulate_imu needs an rng when noise is on")
        n = len(t)
        dt = 1.0 / rate_hz
        sg = noise.gyroscope_noise_density * np.sqrt(rate_hz)
        sa = noise.accelerometer_noise_density * np.sqrt(rate_hz)
        bg0 = rng.normal(0, 0.002, 3) if initial_bias else np.zeros(3)
        ba0 = rng.normal(0, 0.02, 3) if initial_bias else np.zeros(3)
        steps_g = rng.standard_normal((n, 3)) * noise.gyroscope_random_walk * np.sqrt(dt)
        steps_a = rng.standard_normal((n, 3)) * noise.accelerometer_random_walk * np.sqrt(dt)
        steps_g[0] = steps_a[0] = 0.0
        bg = bg0 + np.cumsum(steps_g, axis=0)
        ba = ba0 + np.cumsum(steps_a, axis=0)
        gyro = gyro + bg + rng.standard_normal((n, 3)) * sg
        acc = acc + ba + rng.standard_normal((n, 3)) * sa
    return ImuSamples(t_us, gyro, acc)
