"""Physics of the simulated rig: slider motion, tissue, and what the load cell sees.

The tissue is the paper's proposed model, integrated in small fixed sub-steps
(default 0.5 ms), or a relaxation modulus under an indenter (`tissue.material`,
sim_device.material). Hidden effects are mechanisms added to that chain, never calls to
the analysis code: a second Maxwell branch, a frame spring in series, guide
friction, a cable preload, load-cell drift and a delay line in the sensor; and tissue
physics the paper's model lacks: relaxation that speeds up with the loading speed, a
power-law (fractional Maxwell) branch, and preconditioning over repeated loadings.

Everything is lazily advanced: `advance(t_s)` integrates up to time `t_s`, so the
same object serves the in-process devices (virtual or real clock) and the devices
on the wire.
"""

from __future__ import annotations

import math
import threading
from collections import deque

import numpy as np
from rig.sim.material import Material
from rig.sim.params import STANDARD_GRAVITY, SimParams


class SliderMotion:
    """A stepper axis executing trapezoidal moves; position in mm, speeds in mm/s."""

    def __init__(self, accel_mm_s2: float, stop_decel_mm_s2: float, start_mm: float = 0.0) -> None:
        self.position_mm = start_mm
        self.velocity_mm_s = 0.0
        self.target_mm = start_mm
        self.speed_mm_s = 0.0
        self.accel_mm_s2 = accel_mm_s2
        self.default_accel_mm_s2 = accel_mm_s2
        self.stop_decel_mm_s2 = stop_decel_mm_s2
        self.moving = False
        self.stopping = False

    def move_to(self, target_mm: float, speed_mm_s: float, accel_mm_s2: float | None = None) -> None:
        self.target_mm = target_mm
        self.speed_mm_s = abs(speed_mm_s)
        self.accel_mm_s2 = accel_mm_s2 or self.default_accel_mm_s2
        self.stopping = False
        self.moving = self.speed_mm_s > 0 and (target_mm != self.position_mm or self.velocity_mm_s != 0)

    def stop(self) -> None:
        """Decelerate at the stop rate; a stop is never cancelled by anything but a new move."""
        if self.moving:
            self.stopping = True

    def step(self, dt: float) -> None:
        if not self.moving:
            self.velocity_mm_s = 0.0
            return
        v = self.velocity_mm_s
        if self.stopping:
            dv = self.stop_decel_mm_s2 * dt
            v = 0.0 if abs(v) <= dv else v - math.copysign(dv, v)
            self.position_mm += v * dt
            self.velocity_mm_s = v
            if v == 0.0:
                self.moving = self.stopping = False
                self.target_mm = self.position_mm
            return
        d = self.target_mm - self.position_mm
        # Fastest speed from which we can still stop at the target in whole sub-steps (the
        # discrete form of v^2 = 2 a d, so the last step lands without a velocity jump).
        a_dt = self.accel_mm_s2 * dt
        v_brake = math.sqrt(2.0 * self.accel_mm_s2 * abs(d) + 0.25 * a_dt * a_dt) - 0.5 * a_dt
        speed = self.speed_mm_s
        v_des = math.copysign(v_brake if v_brake < speed else speed, d)
        # the change is clipped to one sub-step's acceleration (`min`'s and `max`'s own rules)
        dv = v_des - v
        dv = dv if dv < a_dt else a_dt
        v += dv if dv > -a_dt else -a_dt
        step = v * dt
        if abs(step) >= abs(d) or abs(d) < 1e-9:
            self.position_mm = self.target_mm
            self.velocity_mm_s = 0.0
            self.moving = False
        else:
            self.position_mm += step
            self.velocity_mm_s = v


class SimRig:
    """Tissue, slider and sensor chain, integrated to any requested time."""

    def __init__(self, params: SimParams | None = None) -> None:
        self.params = p = params or SimParams()
        self.dt = p.substep_ms / 1000.0
        self.lock = threading.RLock()  # wire servers and in-process devices may share one rig
        self.n = 0  # sub-steps done; t = n * dt
        self.slider = SliderMotion(p.slider.accel_mm_s2, p.slider.stop_decel_mm_s2, p.slider.start_mm)
        self.rng = np.random.default_rng(p.seed)
        tp = p.tissue
        self._a1 = math.exp(-self.dt / tp.tau1_s)
        fx = p.effects
        self._a2 = math.exp(-self.dt / fx.relaxation2.tau_m_s) if fx.relaxation2 else 0.0
        self.f1_N = 0.0  # proposed-model branch (first-order lag state)
        self.f2_N = 0.0  # second Maxwell branch
        self.tissue_force_N = 0.0
        self.peak_tissue_force_N = 0.0  # the most the tissue carried since take_peak_force_N()
        self.indentation_m = 0.0
        self.probe_velocity_mm_s = 0.0
        self.sensor_force_N = 0.0  # what the bridge outputs before noise (delayed if configured)
        self._offset_on = False
        self._lp_N = 0.0  # the indicator's low-pass filter state, and when it last ran
        self._lp_t_s: float | None = None
        delay = fx.delay.delay_s if fx.delay else 0.0
        n_delay = round(delay / self.dt)
        self._delay_line: deque[float] | None = deque([0.0] * (n_delay + 1), maxlen=n_delay + 1) \
            if n_delay > 0 else None
        self._surface_mm = tp.surface_mm + (fx.contact_offset.x0_mm if fx.contact_offset else 0.0)
        self._probe_mm = self.slider.position_mm
        self._peak_rate_m_s = 0.0  # fastest indentation speed of the current contact
        self._loadings = fx.preconditioning.done if fx.preconditioning else 0
        self._stiffness = 1.0
        self._last_read_N = 0.0  # the load cell's last conversion, which a frozen cell repeats
        self._stuck_N: float | None = None  # a faulty cell's value (None: the cell is sound)
        self._stuck_t_s = 0.0
        self._soften()
        self._frac_modes = fractional_modes(fx.fractional, self.dt) if fx.fractional else None
        self._material = Material(tp.material, self.dt) if tp.material else None
        self._frac_N = np.zeros(0 if self._frac_modes is None else len(self._frac_modes[0]))

    @property
    def t_s(self) -> float:
        return self.n * self.dt

    def advance(self, t_s: float) -> None:
        """Integrate forward to `t_s` (never backwards)."""
        n_target = math.floor(t_s / self.dt + 1e-9)
        with self.lock:
            substep = self._substep
            for n in range(self.n, n_target):
                substep()
                self.n = n + 1

    def _substep(self) -> None:
        p, dt = self.params, self.dt
        fx = p.effects
        slider = self.slider
        slider.step(dt)
        # Frame compliance: the frame spring shortens under the force it carries, so the probe
        # lags the slider. Probe and force are solved together in each sub-step (implicitly):
        # taking last sub-step's force instead oscillates and grows once the tissue's damping
        # over its relaxation time (tau2 x / tau1) exceeds the frame's stiffness.
        probe_mm = slider.position_mm
        if fx.compliance:
            probe_mm = self._probe_through_frame(probe_mm, fx.compliance.k_frame_N_per_m)
        self.probe_velocity_mm_s = (probe_mm - self._probe_mm) / dt
        self._probe_mm = probe_mm
        x, f1, f2, total, peak, frac_N, material = self._tissue_at(probe_mm)
        if self._material is not None:
            self._material.commit(material)
        if x == 0.0 and self.indentation_m > 0.0:  # a loading ends: the probe left the surface
            self._loadings += 1
            self._soften()
            peak = 0.0
        self.indentation_m = x
        self.f1_N, self.f2_N, self.tissue_force_N = f1, f2, total
        if total > self.peak_tissue_force_N:
            self.peak_tissue_force_N = total
        self._peak_rate_m_s = peak
        if frac_N is not None:
            self._frac_N = frac_N
        # What the load cell behind the probe carries.
        sensed = self.tissue_force_N
        if fx.friction:
            fr = fx.friction
            sensed += fr.force_N * math.tanh(self.probe_velocity_mm_s / fr.v_smooth_mm_s)
        if fx.offset:
            if not self._offset_on and abs(slider.position_mm - p.slider.start_mm) > fx.offset.after_mm:
                self._offset_on = True
            if self._offset_on:
                sensed += fx.offset.force_N
        if fx.drift:
            sensed += fx.drift.rate_N_per_s * (self.n + 1) * dt
        if self._delay_line is not None:
            self._delay_line.append(sensed)
            sensed = self._delay_line[0]
        self.sensor_force_N = sensed

    def take_peak_force_N(self) -> float:
        """The most the tissue carried since the last call (the truth a force limit is about:
        a tare or an offset may hide part of it from the load cell)."""
        with self.lock:
            peak, self.peak_tissue_force_N = self.peak_tissue_force_N, self.tissue_force_N
        return peak

    def _soften(self) -> None:
        pc = self.params.effects.preconditioning
        if pc:
            self._stiffness = 1.0 - pc.softening * (1.0 - math.exp(-self._loadings / pc.trials))

    def _tissue_at(self, probe_mm: float) -> tuple[float, float, float, float, float, np.ndarray | None,
                                                   dict | None]:
        """Indentation, the relaxing and parallel branches, the total tissue force, and the
        state to keep (the fastest indentation rate of this contact, the power-law branch's
        modes, the material's state), after this sub-step if the probe ends it at `probe_mm`
        (nothing is changed: the frame's solve tries several probe positions).

        Called some 200,000 times a simulated minute, so written for the interpreter: `a if c
        else b` where `max` would be called (the same number, `max`'s own rule, NaN included)."""
        tp, dt, fx = self.params.tissue, self.dt, self.params.effects
        d = probe_mm - self._surface_mm
        x = (0.0 if d < 0.0 else d) / 1000.0
        xdot = (x - self.indentation_m) / dt
        material = None
        if self._material is not None:  # a modulus under the indenter, in place of the lumped drive
            drive, material = self._material.trial(x)
            drive *= self._stiffness * self.params.faults.stiffness_scale
        elif x > 0.0:
            scale = self._stiffness * self.params.faults.stiffness_scale
            drive = scale * ((tp.k1_N_per_m3 * x + tp.k2_N_per_m2) * x + tp.k3_N_per_m) * x \
                + tp.tau2_N_s_per_m2 * x * xdot
        else:
            drive = 0.0
        a1, peak = self._a1, self._peak_rate_m_s
        if fx.speed_relaxation and x > 0.0:
            sr = fx.speed_relaxation
            peak = xdot if xdot > peak else peak
            ref = sr.ref_speed_mm_s / 1000.0
            slowest = 1e-3 * ref
            tau = tp.tau1_s * (ref / (slowest if slowest > peak else peak)) ** sr.exponent
            a1 = math.exp(-dt / tau)
        # Exact discretisation of f + tau1 df/dt = drive over one sub-step (drive held).
        # The tissue cannot pull on the probe: when it would, the surface separates and the
        # branch recovers freely instead of storing tension. The material relaxes in its own
        # modulus: no lag after it.
        f1 = drive + (self.f1_N - drive) * a1 if material is None else drive
        f1 = 0.0 if f1 < 0.0 else f1
        f2 = 0.0
        if fx.relaxation2 and x > 0.0:
            f2 = self.f2_N * self._a2 + fx.relaxation2.k_m_N_per_m * (xdot * dt)
            f2 = 0.0 if f2 < 0.0 else f2
        frac_N, frac = None, 0.0
        if self._frac_modes is not None:
            decay, gain = self._frac_modes
            # out of contact the branch recovers freely; in contact it may push or pull on the
            # rest of the tissue, only the sum on the probe cannot pull
            frac_N = self._frac_N * decay + gain * xdot if x > 0.0 else np.zeros_like(decay)
            frac = float(frac_N.sum())
        total = 0.0
        if x > 0.0:
            total = f1 + f2 + frac
            total = 0.0 if total < 0.0 else total
        return x, f1, f2, total, peak, frac_N, material

    def _probe_through_frame(self, slider_mm: float, k_frame_N_per_m: float) -> float:
        """The probe position p with p = slider - f(p) / k_frame: the tissue force grows with
        p, so the root is unique and lies between the slider and where the slider's own
        force would push it; bisection guarded regula falsi to well below an encoder step."""
        def gap(p: float) -> float:
            return p - slider_mm + 1000.0 * self._tissue_at(p)[3] / k_frame_N_per_m

        hi, g_hi = slider_mm, gap(slider_mm)
        if g_hi <= 0.0:
            return slider_mm
        lo = slider_mm - 1000.0 * self._tissue_at(slider_mm)[3] / k_frame_N_per_m
        g_lo = gap(lo)
        if g_lo >= 0.0:
            return lo
        side = 0
        for _ in range(100):
            p = (lo * g_hi - hi * g_lo) / (g_hi - g_lo)
            g = gap(p)
            if abs(g) <= 1e-9 or hi - lo <= 1e-9:
                return p
            if g > 0.0:
                hi, g_hi = p, g
                if side == 1:
                    g_lo *= 0.5  # Illinois: a stale end is halved so the bracket keeps shrinking
                side = 1
            else:
                lo, g_lo = p, g
                if side == -1:
                    g_hi *= 0.5
                side = -1
        return p

    def read_force_N(self) -> float:
        """One load-cell conversion: the bridge force plus Gaussian noise, quantised; or what a
        faulty cell reports (`FaultParams.loadcell_frozen`, `loadcell_noiseless`)."""
        lc, faults = self.params.loadcell, self.params.faults
        with self.lock:
            if faults.loadcell_frozen or faults.loadcell_noiseless:
                return self._faulty_reading(faults.loadcell_frozen, lc.resolution_N)
            self._stuck_N = None
            value = lc.gain * (self.sensor_force_N + lc.mass_g * 1e-3 * STANDARD_GRAVITY) \
                + (self.rng.normal(0.0, lc.noise_N) if lc.noise_N else 0.0)
            if lc.lowpass_Hz > 0:
                value = self._lowpass(value, lc.lowpass_Hz)
        if lc.resolution_N:
            value = round(value / lc.resolution_N) * lc.resolution_N
        self._last_read_N = value
        return value

    def _faulty_reading(self, frozen: bool, resolution_N: float) -> float:
        """Frozen: the last reading again, on every line. Noiseless: no noise, and the bridge's
        output drifts towards the force only with a 20 s time constant (a saturated or
        disconnected amplifier reads steady and plausible, not zero)."""
        if self._stuck_N is None:
            self._stuck_N, self._stuck_t_s = self._last_read_N, self.t_s
        if not frozen:
            a = math.exp(-max(self.t_s - self._stuck_t_s, 0.0) / 20.0)
            self._stuck_N = a * self._stuck_N + (1.0 - a) * self.sensor_force_N
            self._stuck_t_s = self.t_s
        value = self._stuck_N
        return round(value / resolution_N) * resolution_N if resolution_N else value

    def _lowpass(self, value: float, cutoff_Hz: float) -> float:
        """First-order low-pass over the time since the last conversion (y + tau dy/dt = u)."""
        t = self.t_s
        if self._lp_t_s is None:
            self._lp_N = value
        else:
            a = math.exp(-2.0 * math.pi * cutoff_Hz * max(t - self._lp_t_s, 0.0))
            self._lp_N = a * self._lp_N + (1.0 - a) * value
        self._lp_t_s = t
        return self._lp_N

    def feedback_position_mm(self) -> float:
        """The encoder's view of the slider: whole steps only."""
        spm = self.params.slider.steps_per_mm
        return round(self.slider.position_mm * spm) / spm


def fractional_modes(fr, dt: float, per_decade: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """The fractional Maxwell branch as a ladder of Maxwell modes, per sub-step: each mode's decay
    factor and its gain on the indentation rate.

    Its relaxation modulus k E_a(-(t/tau)^a) is a continuous mixture of exponentials
    exp(-r t / tau) whose weight over r has the closed-form distribution function
        F(r) = (arctan((r^a + cos(pi a)) / sin(pi a)) - arctan(cot(pi a))) / (pi a),
    so each mode carries the exact weight of its cell of rates; rates from 1e-5/s (slower ones
    act as springs over any trial) to ten per sub-step (faster ones relax within a step).
    """
    a = fr.alpha
    lo, hi = math.log10(1e-5 * fr.tau_s), math.log10(10.0 * fr.tau_s / dt)
    n = max(2, math.ceil((hi - lo) * per_decade))
    edges = np.logspace(lo, hi, n + 1)
    r = np.sqrt(edges[:-1] * edges[1:])
    s, c = math.sin(math.pi * a), math.cos(math.pi * a)
    cdf = (np.arctan((edges ** a + c) / s) - math.atan2(c, s)) / (math.pi * a)
    cdf[0], cdf[-1] = 0.0, 1.0  # the tails go to the end cells
    weight = np.diff(cdf)
    rate = r / fr.tau_s
    decay = np.exp(-rate * dt)
    # f_i + df_i/dt / rate_i = (k w_i / rate_i) dx/dt, exact for dx/dt held over the sub-step
    gain = fr.k_N_per_m * weight * (-np.expm1(-rate * dt)) / rate
    return decay, gain
