"""An analytic model of the air flow around a ball moving through still air (the course report's
scene), in the ball's frame: air streams past the ball in +x.

The velocity at a point (world units; the ball has radius :data:`BALL_RADIUS` at the origin) is

* the potential flow of a uniform stream ``U`` around a sphere, damped to zero inside a thin
  boundary layer at the ball's surface, with a velocity deficit (the wake) behind it;
* a train of vortex rings shed behind the ball, drifting, growing and tilting downstream: each
  ring is the curl of an azimuthal vector potential ``A = S rho exp(-((rho-a)^2+zeta^2)/(2 s^2))``
  around its own axis, so it is divergence-free by construction;
* a pair of counter-rotating streamwise vortex tubes meandering behind the ball (curl of a
  streamwise vector potential, divergence-free as well);
* a seeded random divergence-free perturbation: the curl of a sum of Fourier modes of a vector
  potential with a Kolmogorov-like spectrum, confined to the wake by a smooth envelope.

So the Q-criterion shows eddies of several sizes: big rings, thinner tubes, small turbulent
blobs. Everything is a closed-form NumPy expression, evaluated point by point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BALL_RADIUS = 0.5
FREESTREAM = 0.04          # world units per time unit; speeds are of the order of 0.01-0.1
DOMAIN_LO = (-2.0, -2.0, -2.0)
DOMAIN_HI = (6.0, 2.0, 2.0)
BOUNDARY_LAYER = 0.06      # thickness of the damping layer at the ball's surface


@dataclass(frozen=True)
class Ring:
    centre: np.ndarray       # world position
    axis: np.ndarray         # unit vector (the ring's own zeta axis)
    radius: float
    core: float              # Gaussian core width s
    strength: float          # S, in units of the free stream


@dataclass(frozen=True)
class Mode:
    k: np.ndarray            # wave vector (radians per world unit)
    a: np.ndarray            # amplitude of the vector potential
    phase: float


class SphereWakeFlow:
    """The velocity model; ``seed`` fixes the rings' jitter and the perturbation."""

    def __init__(self, seed: int = 0):
        rng = np.random.default_rng(seed)
        self.rings = []
        drift = np.zeros(2)
        for k in range(11):
            drift += rng.normal(0.0, 0.07, 2)
            x = 0.85 + 0.45 * k + rng.uniform(-0.05, 0.05)
            tilt = np.radians(rng.uniform(5.0, 28.0))
            turn = rng.uniform(0.0, 2.0 * np.pi)
            axis = np.array([np.cos(tilt), np.sin(tilt) * np.cos(turn), np.sin(tilt) * np.sin(turn)])
            self.rings.append(Ring(centre=np.array([x, drift[0], drift[1]]), axis=axis,
                                   radius=0.34 + 0.035 * k, core=0.075 + 0.006 * k,
                                   strength=(0.32 - 0.012 * k) * (1.0 if k % 2 == 0 else 0.85)))
        self.modes = []
        for _ in range(28):
            kmag = np.exp(rng.uniform(np.log(3.0), np.log(22.0)))
            direction = rng.normal(size=3)
            direction /= np.linalg.norm(direction)
            amp = rng.normal(size=3)
            amp -= direction * (amp @ direction)
            amp *= 0.9 * kmag ** (-11.0 / 6.0) / np.linalg.norm(amp)
            self.modes.append(Mode(k=kmag * direction, a=amp, phase=rng.uniform(0, 2 * np.pi)))
        self.tube_phase = rng.uniform(0, 2 * np.pi, 2)

    # ------------------------------------------------------------------ the velocity
    def velocity(self, p: np.ndarray) -> np.ndarray:
        """Velocity ``(N, 3)`` at world points ``p`` ``(N, 3)``."""
        p = np.asarray(p, dtype=np.float64)
        v = self._potential(p)
        extra = np.zeros_like(p)
        for ring in self.rings:
            extra += self._ring(p, ring)
        extra += self._tubes(p)
        extra += self._perturbation(p)
        return v + FREESTREAM * extra * self._outside_ball(p)[:, None]

    def _outside_ball(self, p):
        r = np.linalg.norm(p, axis=1)
        d = np.maximum(r - BALL_RADIUS, 0.0)
        return 1.0 - np.exp(-(d / BOUNDARY_LAYER) ** 2)

    def _potential(self, p):
        """Uniform stream past the ball, damped at its surface, with a wake deficit."""
        R, U = BALL_RADIUS, FREESTREAM
        r = np.maximum(np.linalg.norm(p, axis=1), 1e-9)
        x = p[:, 0]
        v = np.zeros_like(p)
        v[:, 0] = 1.0
        v -= 0.5 * R ** 3 * (np.array([1.0, 0.0, 0.0]) / r[:, None] ** 3
                             - 3.0 * x[:, None] * p / r[:, None] ** 5)
        # Wake: slower air in a widening tube behind the ball.
        rho2 = p[:, 1] ** 2 + p[:, 2] ** 2
        width = 0.45 + 0.12 * np.maximum(x, 0.0)
        onset = 0.5 * (1.0 + np.tanh((x - 0.2) / 0.3))
        v[:, 0] -= 0.55 * onset * np.exp(-rho2 / (2.0 * width ** 2)) / (1.0 + 0.15 * np.maximum(x, 0))
        return U * v * self._outside_ball(p)[:, None]

    def _ring(self, p, ring: Ring):
        reach = ring.radius + 5.0 * ring.core
        d = p - ring.centre
        near = np.flatnonzero(np.all(np.abs(d) < reach, axis=1))
        out = np.zeros_like(p)
        if len(near) == 0:
            return out
        d = d[near]
        zeta = d @ ring.axis
        radial = d - zeta[:, None] * ring.axis
        rho = np.linalg.norm(radial, axis=1)
        e_rho = radial / np.maximum(rho, 1e-12)[:, None]
        s2 = ring.core ** 2
        g = ring.strength * np.exp(-((rho - ring.radius) ** 2 + zeta ** 2) / (2.0 * s2))
        # v = curl(A_phi e_phi), A_phi = S rho exp(-q):
        #   v_rho = -dA_phi/dzeta,  v_zeta = (1/rho) d(rho A_phi)/drho
        v_rho = g * rho * zeta / s2
        v_zeta = g * (2.0 - rho * (rho - ring.radius) / s2)
        out[near] = v_rho[:, None] * e_rho + v_zeta[:, None] * ring.axis
        return out

    def _tubes(self, p):
        """Two counter-rotating streamwise tubes: v = curl(A_x e_x) = (0, dA/dz, -dA/dy)."""
        x = p[:, 0]
        out = np.zeros_like(p)
        along = 0.5 * (1.0 + np.tanh((x - 0.6) / 0.25)) * np.exp(-np.maximum(x - 1.0, 0) / 3.5)
        sel = np.flatnonzero(along > 1e-6)
        if len(sel) == 0:
            return out
        xs, ys, zs, env = x[sel], p[sel, 1], p[sel, 2], along[sel]
        for sign, phase in zip((1.0, -1.0), self.tube_phase):
            yc = sign * (0.22 + 0.05 * xs) + 0.08 * np.sin(1.7 * xs + phase)
            zc = 0.1 * np.cos(1.3 * xs + phase)
            s2 = (0.06 + 0.012 * np.maximum(xs, 0)) ** 2
            dy, dz = ys - yc, zs - zc
            psi = sign * 0.05 * env * np.exp(-(dy * dy + dz * dz) / (2.0 * s2))
            out[sel, 1] += psi * (-dz / s2)
            out[sel, 2] -= psi * (-dy / s2)
        return out

    def _perturbation(self, p):
        """curl(E * sum_m a_m sin(k_m . p + phase_m)) with the wake envelope E."""
        x = p[:, 0]
        rho2 = p[:, 1] ** 2 + p[:, 2] ** 2
        width = 0.5 + 0.12 * np.maximum(x, 0.0)
        onset = 0.5 * (1.0 + np.tanh((x - 0.8) / 0.4))
        env = onset * np.exp(-rho2 / (2.0 * width ** 2))
        out = np.zeros_like(p)
        # Below 1e-3 of its peak the perturbation is left out (a negligible step in the field).
        sel = np.flatnonzero(env > 1e-3)
        if len(sel) == 0:
            return out
        q = p[sel]
        e = env[sel]
        # Gradient of the envelope (onset' * gauss, onset * gauss').
        dx = 0.5 / 0.4 * (1.0 - np.tanh((q[:, 0] - 0.8) / 0.4) ** 2) * np.exp(
            -rho2[sel] / (2.0 * width[sel] ** 2))
        dwidth = np.where(q[:, 0] > 0, 0.12, 0.0)
        dx += e * rho2[sel] / width[sel] ** 3 * dwidth
        grad_e = np.stack([dx, -e * q[:, 1] / width[sel] ** 2, -e * q[:, 2] / width[sel] ** 2],
                          axis=1)
        k = np.array([m.k for m in self.modes])
        a = np.array([m.a for m in self.modes])
        # Single precision is plenty for the trigonometry and twice as fast.
        arg = (q @ k.T + np.array([m.phase for m in self.modes])).astype(np.float32)
        A = np.sin(arg) @ a.astype(np.float32)
        curl = np.cos(arg) @ np.cross(k, a).astype(np.float32)
        out[sel] = 2.2 * (e[:, None] * curl + np.cross(grad_e, A))
        return out
