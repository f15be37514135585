"""Smooth body trajectories ``T_world_body(t)`` with analytic derivatives.

Every coordinate is a :class:`Sinusoids` (constant + linear term + sum of sines, so C-infinity):
the position ``p(t)`` in the world (z up) and the ZYX Euler angles of the body (yaw ``psi``
about world z, then pitch ``theta`` about y, then roll ``phi`` about x):
``R_world_body = Rz(psi) Ry(theta) Rx(phi)``. The body (IMU) frame is x forward, y left, z up,
so a level body with zero yaw looks along world +x. Velocity, acceleration and the body angular
velocity come in closed form (no finite differences), which makes the simulated IMU exact.

Kinds (generators take the free space ``lo, hi`` of a scene and fit inside it):

* ``handheld``: slow wandering, 30-60 deg/s; ``loop=True`` returns exactly to its start.
* ``shake``: handheld drift plus 2-5 Hz rotational shaking (peaks of several hundred deg/s,
  as TUM-VIE mocap-shake) and small translational jitter.
* ``spin``: rotation in place about the vertical axis with a hovering wobble (the paper's HDR
  spin); whole turns, so it ends where it started.
* ``drone8``: a figure eight over ~5 m^2 at constant height, banking with the acceleration.
* ``slider``: a straight rest-to-rest glide sideways, fixed orientation.
* ``static``: constant pose.

Any kind can stop and hold still (:class:`Pauses`, ``SequenceSpec.pauses``): the camera slows to a halt,
stands for a while and then goes on along the same path, as a hand-held camera put down for a moment
does. The time warp is C2, so the IMU still sees a continuous acceleration.

Example:
    >>> traj = make_trajectory("handheld", np.random.default_rng(0), 2.0, np.array([-1., -1, 1]), np.array([1., 1, 2]))
    >>> traj.pose7(np.array([0.0, 1.0])).shape
    (2, 7)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import DataError

TRAJECTORY_KINDS = ("handheld", "shake", "spin", "drone8", "slider", "static")
GRAVITY = 9.81


@dataclass
class Sinusoids:
    """``f(t) = c0 + c1 t + sum_k amp_k sin(omega_k t + phase_k)`` (t in seconds).

    Attributes:
        c0, c1: constant and linear coefficient.
        amp, omega, phase: (K,) amplitudes, angular frequencies (rad/s) and phases (rad).
    """

    c0: float = 0.0
    c1: float = 0.0
    amp: np.ndarray = field(default_factory=lambda: np.zeros(0))
    omega: np.ndarray = field(default_factory=lambda: np.zeros(0))
    phase: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        self.amp = np.atleast_1d(np.asarray(self.amp, np.float64))
        self.omega = np.atleast_1d(np.asarray(self.omega, np.float64))
        self.phase = np.atleast_1d(np.asarray(self.phase, np.float64))

    def __call__(self, t: np.ndarray, order: int = 0) -> np.ndarray:
        """The ``order``-th time derivative at times ``t`` (s), shape of ``t``."""
        t = np.asarray(t, np.float64)
        arg = t[..., None] * self.omega + self.phase
        # d^n/dt^n sin(x) = omega^n sin(x + n pi/2)
        s = (self.amp * self.omega ** order * np.sin(arg + order * np.pi / 2)).sum(axis=-1)
        if order == 0:
            return self.c0 + self.c1 * t + s
        if order == 1:
            return self.c1 + s
        return s

    def shifted(self, extra: "Sinusoids") -> "Sinusoids":
        """The sum of two such functions."""
        return Sinusoids(self.c0 + extra.c0, self.c1 + extra.c1, np.concatenate([self.amp, extra.amp]),
                         np.concatenate([self.omega, extra.omega]), np.concatenate([self.phase, extra.phase]))


def _smootherstep(x: np.ndarray, order: int = 0) -> np.ndarray:
    """``S(x) = 6x^5 - 15x^4 + 10x^3`` on [0, 1] (0 and 1 with zero first and second derivative at the
    ends): its integral (``order=-1``), value (0) or derivative (1)."""
    x = np.clip(x, 0.0, 1.0)
    if order == -1:
        return x ** 6 - 3 * x ** 5 + 2.5 * x ** 4
    if order == 0:
        return x ** 3 * (10 - 15 * x + 6 * x * x)
    return 30 * x * x * (1 - x) ** 2


@dataclass
class Pauses:
    """A C2 time warp ``s(t)`` that stops the motion: ``T_world_body`` at time ``t`` is the underlying
    path's at ``s(t)``.

    Around each stop, the path's speed ``s'(t) = 1 - b(t)`` falls to zero over ``ramp_s`` before
    ``t_stop_s`` (a smootherstep, so ``s''`` is continuous), stays zero for ``hold_s`` and rises again
    over ``ramp_s``. Each stop consumes ``ramp_s + hold_s`` of wall time without advancing the path.

    Attributes:
        stops: ``(t_stop_s, hold_s)`` pairs in seconds of wall time, sorted and non-overlapping
            (including their ramps).
        ramp_s: slowing (and speeding-up) time in seconds.
    """

    stops: list = field(default_factory=list)
    ramp_s: float = 0.4

    def __post_init__(self) -> None:
        self.stops = sorted((float(a), float(h)) for a, h in self.stops)
        if self.ramp_s <= 0:
            raise DataError(None, f"pause ramp_s must be > 0 s, got {self.ramp_s}")
        end = -np.inf
        for a, h in self.stops:
            if h < 0 or a - self.ramp_s < max(end, 0.0):
                raise DataError(None, f"pauses {self.stops}: each needs hold_s >= 0 and {self.ramp_s} s of ramp after "
                                      f"t=0 and after the previous pause (ramp_s)")
            end = a + h + self.ramp_s

    def __call__(self, t: np.ndarray, order: int = 0) -> np.ndarray:
        """``s(t)`` (order 0, s), ``s'(t)`` (1) or ``s''(t)`` (2, 1/s) at wall times ``t`` (s)."""
        t = np.asarray(t, np.float64)
        r = self.ramp_s
        out = t.copy() if order == 0 else (np.ones_like(t) if order == 1 else np.zeros_like(t))
        for a, h in self.stops:
            x_in = (t - (a - r)) / r  # slowing: b rises 0 -> 1 over x_in in [0, 1]
            x_out = (t - (a + h)) / r  # speeding up: b falls 1 -> 0 over x_out in [0, 1]
            if order == 0:
                # s = t - integral of b: r I(x_in) while slowing, + the hold, + r (1/2 - I(1 - x_out)) after
                held = np.clip(t - a, 0.0, h)
                out -= r * _smootherstep(x_in, -1) + held + r * (0.5 - _smootherstep(1 - x_out, -1)) * (x_out > 0)
            elif order == 1:
                out -= np.where(x_out <= 0, _smootherstep(x_in), _smootherstep(1 - x_out))
            else:
                rising = (x_in > 0) & (x_in < 1)
                falling = (x_out > 0) & (x_out < 1)
                out -= (rising * _smootherstep(x_in, 1) - falling * _smootherstep(1 - x_out, 1)) / r
        return out


@dataclass
class Trajectory:
    """``T_world_body(t)`` from position and ZYX-Euler :class:`Sinusoids`.

    Attributes:
        kind: generator name (see :data:`TRAJECTORY_KINDS`).
        duration_s: length in seconds (evaluation outside ``[0, duration_s]`` is allowed but unused).
        pos: three functions, world x, y, z in metres.
        euler: three functions, yaw, pitch, roll in radians.
        pauses: stops of the motion (None: none); every method evaluates the path at ``pauses(t)`` and
            scales its derivatives by the chain rule.
    """

    kind: str
    duration_s: float
    pos: list[Sinusoids]
    euler: list[Sinusoids]
    pauses: Pauses | None = None

    @property
    def paused(self) -> bool:
        """Whether the motion stops anywhere (``pauses`` with at least one stop)."""
        return self.pauses is not None and bool(self.pauses.stops)

    def _path_time(self, t: np.ndarray) -> np.ndarray:
        """The path's time ``s(t)`` at wall times ``t`` (``t`` itself without pauses)."""
        return self.pauses(t) if self.paused else np.asarray(t, np.float64)

    def kinematics(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Fast single-time evaluation for the simulation loop.

        Returns:
            ``R_world_body`` (3, 3), position (3,) m, velocity (3,) m/s (world), body angular
            velocity (3,) rad/s; identical to :meth:`rotation`, :meth:`position` and
            :meth:`angular_velocity` but with one vectorised pass over all six functions.
        """
        pk = getattr(self, "_packed", None)
        if pk is None:
            fs = list(self.pos) + list(self.euler)
            k = max(1, max(len(f.amp) for f in fs))
            amp, om, ph = (np.zeros((6, k)) for _ in range(3))
            for i, f in enumerate(fs):
                amp[i, :len(f.amp)], om[i, :len(f.omega)], ph[i, :len(f.phase)] = f.amp, f.omega, f.phase
            pk = self._packed = (np.array([f.c0 for f in fs]), np.array([f.c1 for f in fs]), amp, om, ph)
        c0, c1, amp, om, ph = pk
        # the simulation loop's hot path: no warp arrays without pauses
        s_t, ds = (float(self.pauses(t_s)), float(self.pauses(t_s, 1))) if self.paused else (t_s, 1.0)
        arg = s_t * om + ph
        f0 = c0 + c1 * s_t + (amp * np.sin(arg)).sum(1)
        f1 = (c1 + (amp * om * np.cos(arg)).sum(1)) * ds
        psi, th, phi = f0[3:]
        dpsi, dth, dphi = f1[3:]
        cy, sy, cp, sp, cr, sr = np.cos(psi), np.sin(psi), np.cos(th), np.sin(th), np.cos(phi), np.sin(phi)
        R = np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                      [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                      [-sp, cp * sr, cp * cr]])
        w = np.array([dphi - dpsi * sp, dth * cr + dpsi * sr * cp, -dth * sr + dpsi * cr * cp])
        return R, f0[:3], f1[:3], w

    def position(self, t: np.ndarray, order: int = 0) -> np.ndarray:
        """(N, 3) world position (order 0, m), velocity (1, m/s), acceleration (2, m/s²) or, without
        pauses, any higher derivative."""
        if not self.paused:
            return np.stack([f(t, order) for f in self.pos], axis=-1)
        s_t = self.pauses(t)
        if order == 0:
            return np.stack([f(s_t) for f in self.pos], axis=-1)
        ds = self.pauses(t, 1)
        if order == 1:
            return np.stack([f(s_t, 1) * ds for f in self.pos], axis=-1)
        if order == 2:  # d²/dt² f(s(t)) = f''(s) s'^2 + f'(s) s''
            dds = self.pauses(t, 2)
            return np.stack([f(s_t, 2) * ds * ds + f(s_t, 1) * dds for f in self.pos], axis=-1)
        raise ValueError(f"position derivative order must be 0, 1 or 2 on a trajectory with pauses, got {order}")

    def rotation(self, t: np.ndarray) -> np.ndarray:
        """(N, 3, 3) ``R_world_body``."""
        s_t = self._path_time(t)
        psi, th, ph = (f(s_t) for f in self.euler)
        cy, sy, cp, sp, cr, sr = np.cos(psi), np.sin(psi), np.cos(th), np.sin(th), np.cos(ph), np.sin(ph)
        R = np.empty(np.shape(psi) + (3, 3))
        R[..., 0, 0] = cy * cp
        R[..., 0, 1] = cy * sp * sr - sy * cr
        R[..., 0, 2] = cy * sp * cr + sy * sr
        R[..., 1, 0] = sy * cp
        R[..., 1, 1] = sy * sp * sr + cy * cr
        R[..., 1, 2] = sy * sp * cr - cy * sr
        R[..., 2, 0] = -sp
        R[..., 2, 1] = cp * sr
        R[..., 2, 2] = cp * cr
        return R

    def angular_velocity(self, t: np.ndarray) -> np.ndarray:
        """(N, 3) body angular velocity ``omega_body`` in rad/s (what a gyroscope measures).

        For ``R = Rz(psi) Ry(theta) Rx(phi)``: ``omega_body = (phi' - psi' sin(theta),
        theta' cos(phi) + psi' sin(phi) cos(theta), -theta' sin(phi) + psi' cos(phi) cos(theta))``.
        """
        s_t, ds = self._path_time(t), (self.pauses(t, 1) if self.paused else 1.0)
        psi, th, ph = (f(s_t) for f in self.euler)
        dpsi, dth, dph = (f(s_t, 1) * ds for f in self.euler)
        return np.stack([
            dph - dpsi * np.sin(th),
            dth * np.cos(ph) + dpsi * np.sin(ph) * np.cos(th),
            -dth * np.sin(ph) + dpsi * np.cos(ph) * np.cos(th),
        ], axis=-1)

    def pose_matrix(self, t: np.ndarray) -> np.ndarray:
        """(N, 4, 4) ``T_world_body``."""
        t = np.atleast_1d(np.asarray(t, np.float64))
        T = np.zeros(t.shape + (4, 4))
        T[..., :3, :3] = self.rotation(t)
        T[..., :3, 3] = self.position(t)
        T[..., 3, 3] = 1.0
        return T

    def pose7(self, t: np.ndarray) -> np.ndarray:
        """(N, 7) ``tx ty tz qx qy qz qw`` of ``T_world_body`` (the canonical GT format)."""
        t = np.atleast_1d(np.asarray(t, np.float64))
        psi, th, ph = (f(self._path_time(t)) / 2 for f in self.euler)
        cy, sy, cp, sp, cr, sr = np.cos(psi), np.sin(psi), np.cos(th), np.sin(th), np.cos(ph), np.sin(ph)
        q = np.stack([
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy,
        ], axis=-1)
        q *= np.where(q[..., 3:] < 0, -1.0, 1.0)  # canonical sign: qw >= 0
        return np.concatenate([self.position(t), q], axis=-1)


# --------------------------------------------------------------------------------------------
def _random_sines(rng, n, amp_total, f_lo, f_hi, duration=None, loop=False) -> Sinusoids:
    """``n`` sines with amplitudes summing to ``amp_total`` and frequencies in [f_lo, f_hi] Hz.

    With ``loop`` every frequency is a whole multiple of ``1/duration``, so the function
    returns to its start value (and derivatives) at ``t = duration``.
    """
    w = rng.dirichlet(np.ones(n)) * amp_total
    f = rng.uniform(f_lo, f_hi, n)
    if loop:
        f = np.maximum(np.round(f * duration), 1) / duration
    return Sinusoids(0.0, 0.0, w, 2 * np.pi * f, rng.uniform(0, 2 * np.pi, n))


def make_trajectory(kind: str, rng: np.random.Generator, duration_s: float, lo: np.ndarray, hi: np.ndarray,
                    *, loop: bool = False, speed: float = 1.0, loop_period_s: float | None = None) -> Trajectory:
    """Generate a trajectory of a kind inside the free box ``[lo, hi]`` (world, metres).

    Args:
        kind: one of :data:`TRAJECTORY_KINDS`.
        rng: random generator (the trajectory is a function of its state).
        duration_s: length in seconds.
        lo, hi: (3,) corners of the free space the body should stay in.
        loop: make a ``handheld`` trajectory periodic, so that it is back exactly where it
            started after ``loop_period_s`` (others that loop by nature do: ``spin``, ``drone8``).
        speed: scales the frequencies of handheld/shake motion (and spin rate).
        loop_period_s: the period of a looping ``handheld`` trajectory (None: ``duration_s``, so
            it ends where it started). A shorter period makes the camera go round its closed
            path and then retrace its first ``duration_s - loop_period_s`` seconds, as a loop
            recording that continues past its start does.

    Raises:
        DataError: for an unknown kind.
    """
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    mid, half = (lo + hi) / 2, np.maximum((hi - lo) / 2, 0.0)
    T = float(duration_s)
    period = float(loop_period_s) if loop_period_s is not None else T
    if loop and not 0 < period <= T:
        raise DataError(None, f"loop_period_s must lie in (0, duration_s = {T}], got {loop_period_s}")
    if kind not in TRAJECTORY_KINDS:
        raise DataError(None, f"unknown trajectory kind {kind!r}; expected one of {TRAJECTORY_KINDS}")
    yaw0 = rng.uniform(-np.pi, np.pi)
    if kind == "static":
        c = mid + rng.uniform(-0.5, 0.5, 3) * half
        return Trajectory(kind, T, [Sinusoids(c[i]) for i in range(3)],
                          [Sinusoids(yaw0), Sinusoids(rng.uniform(-0.1, 0.1)), Sinusoids(rng.uniform(-0.05, 0.05))])
    if kind in ("handheld", "shake"):
        c = mid + rng.uniform(-0.3, 0.3, 3) * half
        amp = np.minimum(0.45 * half, [0.5, 0.5, 0.15])
        pos = []
        for i in range(3):
            s = _random_sines(rng, 3, amp[i], 0.1 * speed, 0.5 * speed, period, loop)
            s.c0 = c[i] - s(np.zeros(1))[0]  # start at c
            pos.append(s)
        euler = [_random_sines(rng, 3, rng.uniform(0.3, 0.6), 0.08 * speed, 0.4 * speed, period, loop),
                 _random_sines(rng, 2, rng.uniform(0.08, 0.2), 0.1 * speed, 0.5 * speed, period, loop),
                 _random_sines(rng, 2, rng.uniform(0.04, 0.1), 0.1 * speed, 0.5 * speed, period, loop)]
        euler[0].c0 = yaw0
        euler[1].c0 = rng.uniform(-0.1, 0.05)
        if kind == "shake":
            # Rotational shaking: yaw and pitch at 3-6 Hz, amplitudes 0.1-0.35 rad, so peak
            # rates reach A * 2 pi f ~ 300-700 deg/s; translation jitter of 1-3 cm.
            euler[0] = euler[0].shifted(_random_sines(rng, 2, rng.uniform(0.2, 0.35), 3.0 * speed, 6.0 * speed, period, loop))
            euler[1] = euler[1].shifted(_random_sines(rng, 2, rng.uniform(0.1, 0.2), 3.0 * speed, 6.0 * speed, period, loop))
            euler[2] = euler[2].shifted(_random_sines(rng, 1, rng.uniform(0.03, 0.08), 2.0 * speed, 4.0 * speed, period, loop))
            for i in range(3):
                pos[i] = pos[i].shifted(_random_sines(rng, 2, rng.uniform(0.01, 0.03), 3.0 * speed, 6.0 * speed, period, loop))
        return Trajectory(kind, T, pos, euler)
    if kind == "spin":
        c = mid + rng.uniform(-0.3, 0.3, 3) * half
        # ~90-160 deg/s; whole turns (ends where it started) unless too short for one.
        turns = T * speed * rng.uniform(0.25, 0.45)
        turns = float(round(turns)) if turns >= 0.75 else turns
        sign = rng.choice([-1.0, 1.0])
        pos = [Sinusoids(c[i]).shifted(_random_sines(rng, 2, min(0.04, half[i]), 0.3, 1.0, T, True)) for i in range(3)]
        for i, p in enumerate(pos):  # start exactly at c
            p.c0 -= p(np.zeros(1))[0] - c[i]
        euler = [Sinusoids(yaw0, sign * 2 * np.pi * turns / T),
                 Sinusoids(rng.uniform(-0.05, 0.05)).shifted(_random_sines(rng, 2, 0.03, 0.3, 1.5, T, True)),
                 Sinusoids(0.0).shifted(_random_sines(rng, 2, 0.03, 0.3, 1.5, T, True))]
        return Trajectory(kind, T, pos, euler)
    if kind == "drone8":
        # One eight takes 6-9 s (at speed 1); whole eights (closing the loop) when the
        # sequence is long enough, else a part of one at the same pace.
        loops = T * speed / rng.uniform(6.0, 9.0)
        loops = float(round(loops)) if loops >= 0.75 else loops
        w = 2 * np.pi * loops / T
        # Fit the eight's long axis along the longer side of the free space.
        A = min(1.5, 0.95 * max(half[0], half[1]))
        B = min(0.8, 0.95 * min(half[0], half[1]))
        long_x = half[0] >= half[1]
        ph0 = 0.0  # start at the crossing point of the eight
        ax = Sinusoids(mid[0], 0.0, [A if long_x else B], [w if long_x else 2 * w], [ph0])
        ay = Sinusoids(mid[1], 0.0, [B if long_x else A], [2 * w if long_x else w], [ph0])
        z = Sinusoids(np.clip(rng.uniform(1.0, 1.6), lo[2], hi[2]), 0.0, [min(0.1, half[2])], [w], [0.0])
        yaw = Sinusoids(yaw0, 0.0, [0.3], [w], [0.0])
        # A quadrotor tilts along its acceleration: pitch = a_forward / g, roll = -a_left / g
        # (small-angle, expressed in the mean-yaw frame; both stay sums of sines).
        acc_amp_x, acc_amp_y = -ax.amp * ax.omega ** 2, -ay.amp * ay.omega ** 2
        cyaw, syaw = np.cos(yaw0), np.sin(yaw0)
        pitch = Sinusoids(0.0, 0.0, np.concatenate([cyaw * acc_amp_x, syaw * acc_amp_y]) / GRAVITY,
                          np.concatenate([ax.omega, ay.omega]), np.concatenate([ax.phase, ay.phase]))
        roll = Sinusoids(0.0, 0.0, -np.concatenate([-syaw * acc_amp_x, cyaw * acc_amp_y]) / GRAVITY,
                         np.concatenate([ax.omega, ay.omega]), np.concatenate([ax.phase, ay.phase]))
        return Trajectory(kind, T, [ax, ay, z], [yaw, pitch, roll])
    # slider: rest-to-rest glide s(t) = L (t/T - sin(2 pi t/T) / (2 pi)) sideways to the view.
    yaw0 = rng.choice([0.0, np.pi / 2, np.pi, -np.pi / 2]) + rng.uniform(-0.3, 0.3)
    side = np.array([-np.sin(yaw0), np.cos(yaw0), 0.0])  # body y (left) in the world
    extent = np.abs(side[:2]) @ half[:2] if np.any(half[:2] > 0) else 0.0
    L = min(1.5, 1.6 * float(extent)) * rng.choice([-1.0, 1.0])
    c = mid - side * L / 2
    c[2] = np.clip(rng.uniform(0.9, 1.6), lo[2], hi[2])
    pos = [Sinusoids(c[i], L * side[i] / T, [-L * side[i] / (2 * np.pi)], [2 * np.pi / T], [0.0]) for i in range(3)]
    euler = [Sinusoids(yaw0), Sinusoids(rng.uniform(-0.1, 0.1)), Sinusoids(0.0)]
    return Trajectory("slider", T, pos, euler)


def check_inside(traj: Trajectory, scene, T_body_cams: list[np.ndarray], *, margin: float = 0.2,
                 rate_hz: float = 200.0, name: str = "") -> None:
    """Raise unless every camera centre keeps ``margin`` metres from walls and boxes throughout.

    Args:
        traj: the body trajectory.
        scene: a :class:`~aerovis_slam.sim.scene.Scene` (its ``clearance``).
        T_body_cams: (4, 4) camera-to-body transforms (``T_imu_cam``).
        margin: minimum distance in metres.
        rate_hz: checking rate (the motion moves < 1 cm between checks at these speeds).
        name: sequence name for the message.

    Raises:
        DataError: naming the time, camera and position where the trajectory leaves.
    """
    t = np.linspace(0.0, traj.duration_s, max(2, int(traj.duration_s * rate_hz) + 1))
    T_wb = traj.pose_matrix(t)
    for k, T_bc in enumerate(T_body_cams):
        centres = T_wb[:, :3, :3] @ T_bc[:3, 3] + T_wb[:, :3, 3]
        clear = scene.clearance(centres)
        bad = np.flatnonzero(clear < margin)
        if len(bad):
            i = int(bad[0])
            raise DataError(None, f"trajectory {name or traj.kind!r} ({traj.kind}) leaves the free space of scene "
                                  f"seed {scene.seed} at t={t[i]:.2f} s: camera {k} at {np.round(centres[i], 2).tolist()} m "
                                  f"is {clear[i]:.2f} m from a surface (needs >= {margin} m)")
