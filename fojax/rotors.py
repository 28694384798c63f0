"""A quadrotor's four rotors: their layout, the allocation it gives, the vehicle's
authority, and the rotors' first-order lag.

Layout
------
A :class:`Layout` places four rotors in the body frame (``x`` forward, ``y`` left,
``z`` up, the plant's axes) and gives each a spin seen from above (``+1`` counter-
clockwise, ``-1`` clockwise). Rotor ``i`` at ``(x_i, y_i)`` turning at ``w_i`` gives the
thrust ``rho_b w_i^2`` along body ``z``, the torque ``r_i x F_i = rho_b w_i^2 (y_i,
-x_i, 0)`` and the drag torque ``-s_i rho_c w_i^2`` about body ``z`` (a counter-clockwise
rotor drags the body clockwise). The allocation (mixer) is therefore::

    (u_F, tau_x, tau_y, tau_z) = diag(rho_b, rho_b, rho_b, rho_c) G (w_1^2, ..., w_4^2)

    G = [[ 1,    1,    1,    1   ],
         [ y_1,  y_2,  y_3,  y_4 ],
         [-x_1, -x_2, -x_3, -x_4 ],
         [-s_1, -s_2, -s_3, -s_4 ]]

``G`` is geometry only, known before tracing; its inverse is computed once in Python
(float64), so the controllers' inverse allocation ``w^2 = G^-1 (u_F / rho_b, tau_x /
rho_b, tau_y / rho_b, tau_z / rho_c)`` is sixteen multiply-adds with constant
coefficients, whatever ``rho_b`` and ``rho_c`` a draw has. The gyroscopic rotor speed
of eq. (11) is ``Omega_r = sum_i s_i w_i``.

The paper's ``+`` (eq. (10)) is :func:`plus`: rotor 1 at ``(d, 0)``, 2 at ``(0, -d)``, 3 at
``(-d, 0)``, 4 at ``(0, d)``, rotors 1 and 3 counter-clockwise; ``Omega_r = w_1 - w_2 +
w_3 - w_4``. The plant keeps eq. (10)'s closed form for it (a
:class:`fojax.plant.PlantParams` whose ``layout`` is ``None``); :func:`x` is the ``+``
turned by 45 degrees. A layout is static configuration: it is a pytree node with no
leaves (:func:`jax.tree_util.register_static`), carried by ``PlantParams.layout``
through ``jit``, ``vmap`` and ``grad`` as it is.

Authority
---------
:func:`authority`: with every rotor speed in ``[0, w_max]``, the largest thrust over the
weight and the largest torque about each body axis that the rotors give in both
directions (the smaller of the two signs), each torque with the other rotors at zero
speed, as a vehicle's data sheet states it.

Rotor lag
---------
:func:`lag_weights`: each rotor's thrust, ``rho_b w^2``, and with it its drag torque,
follows its command (held over a step) by a first-order lag, ``T q' = q_c - q`` for the
squared speed ``q = w^2``. Over a step of ``dt`` the exact solution is ``q(s) = q_c +
(q_k - q_c) e^(-s/T)``; the plant receives, held over the step, the step's mean of
``q`` through the allocation (and ``Omega_r`` of its square roots), and the next step
starts from ``q(dt)``. The lag is linear in the command: with ideal actuators the
applied thrust and torques are the command filtered by the same lag, and as ``T -> 0``
the mean tends to ``q_c``, the instantaneous rotors.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math

import jax
import numpy as np

__all__ = [
    "SPINS",
    "Authority",
    "Layout",
    "LayoutError",
    "authority",
    "hover_speeds_squared",
    "lag_weights",
    "plus",
    "x",
]

SPINS = {"ccw": 1, "cw": -1}
"""A rotor's spin seen from above, as a vehicle file writes it, and its sign ``s_i``."""


class LayoutError(ValueError):
    """Rotors that do not make a usable quadrotor (the message says why)."""


@jax.tree_util.register_static
@dataclasses.dataclass(frozen=True)
class Layout:
    """Four rotors: ``positions`` ``((x_i, y_i), ...)`` m in the body frame, ``spins``
    ``(s_i, ...)`` (``+1`` counter-clockwise seen from above, ``-1`` clockwise);
    ``name`` says where it comes from (``"plus"``, ``"x"``, ``"rotors"``: listed one by
    one). Hashable, and a pytree with no leaves (static configuration)."""

    positions: tuple[tuple[float, float], ...]
    spins: tuple[int, ...]
    name: str = "rotors"

    def __post_init__(self) -> None:
        if len(self.positions) != 4 or len(self.spins) != 4:
            raise LayoutError(
                f"a quadrotor has four rotors; got {len(self.positions)} positions and "
                f"{len(self.spins)} spins"
            )
        if any(s not in (1, -1) for s in self.spins):
            raise LayoutError(f"each spin must be +1 (ccw) or -1 (cw), got {self.spins}")
        geometry = self.geometry()
        if abs(np.linalg.det(geometry)) < 1e-12 * max(1.0, np.max(np.abs(geometry))) ** 3:
            raise LayoutError(
                "these rotors cannot control roll, pitch, yaw and thrust independently "
                "(their allocation is singular): place them around the centre, not on a "
                "line, and give two of them each spin"
            )

    def geometry(self) -> np.ndarray:
        """``G`` ``(4, 4)`` float64 (module docstring): the allocation without
        ``rho_b`` and ``rho_c``."""
        xs = [p[0] for p in self.positions]
        ys = [p[1] for p in self.positions]
        return np.array(
            [[1.0] * 4, ys, [-v for v in xs], [-float(s) for s in self.spins]], np.float64
        )

    def inverse(self) -> np.ndarray:
        """``G^-1`` ``(4, 4)`` float64 (cached)."""
        return _inverse(self)

    def arm(self) -> float:
        """The mean distance of the rotors from the centre (m)."""
        return float(np.mean([math.hypot(*p) for p in self.positions]))

    def allocation(self, thrust_factor: float, drag_factor: float) -> np.ndarray:
        """The mixer ``M`` ``(4, 4)`` float64: ``(u_F, tau) = M w^2``."""
        scale = np.array([thrust_factor] * 3 + [drag_factor], np.float64)
        return scale[:, None] * self.geometry()

    def to_bytes(self) -> bytes:
        """The layout serialised (an exported program's tree, :mod:`fojax.export_cache`)."""
        return json.dumps([self.positions, self.spins, self.name]).encode()

    @classmethod
    def from_bytes(cls, data: bytes) -> Layout:
        positions, spins, name = json.loads(bytes(data))
        return cls(tuple(tuple(p) for p in positions), tuple(spins), name)

    def to_dict(self) -> dict:
        """The layout as a file or a record states it."""
        if self.name in ("plus", "x"):
            return {"configuration": self.name, "arm_length": self.arm()}
        spin = {1: "ccw", -1: "cw"}
        return {"rotors": [{"position": list(p), "spin": spin[s]}
                           for p, s in zip(self.positions, self.spins, strict=True)]}  # fmt: skip


@functools.cache
def _inverse(layout: Layout) -> np.ndarray:
    inverse = np.linalg.inv(layout.geometry())
    # exact zeros where the geometry's symmetry gives them (skipped in the plant's sums)
    inverse[np.abs(inverse) < 1e-12 * np.max(np.abs(inverse))] = 0.0
    return inverse


def plus(arm: float) -> Layout:
    """The paper's ``+`` (eq. (10)) at ``arm`` m: rotors 1-4 at ``(d, 0)``, ``(0, -d)``,
    ``(-d, 0)``, ``(0, d)``; 1 and 3 counter-clockwise."""
    d = float(arm)
    return Layout(((d, 0.0), (0.0, -d), (-d, 0.0), (0.0, d)), (1, -1, 1, -1), "plus")


def x(arm: float) -> Layout:
    """The ``+`` of :func:`plus` turned by 45 degrees about ``z``: rotors at
    ``(d / sqrt 2) (1, 1)``, ``(1, -1)``, ``(-1, -1)``, ``(-1, 1)``; diagonal pairs spin
    alike."""
    h = float(arm) / math.sqrt(2.0)
    return Layout(((h, h), (h, -h), (-h, -h), (-h, h)), (1, -1, 1, -1), "x")


def hover_speeds_squared(layout: Layout, mass: float, gravity: float,
                         thrust_factor: float) -> np.ndarray:  # fmt: skip
    """``w_i^2`` ``(4,)`` (rad^2/s^2) of level hover: thrust ``m g``, no torque."""
    return layout.inverse()[:, 0] * (mass * gravity / thrust_factor)


@dataclasses.dataclass(frozen=True)
class Authority:
    """What a vehicle's rotors can do at ``w_max``: ``thrust_to_weight`` (full thrust
    over the weight) and ``max_torque`` ``(roll, pitch, yaw)`` N m, the largest torque
    about each body axis in both directions (module docstring); ``None`` for rotors
    without a speed limit. ``hover_speed`` rad/s: the fastest rotor's speed in hover."""

    thrust_to_weight: float | None
    max_torque: tuple[float, float, float] | None
    hover_speed: float

    def to_dict(self) -> dict:
        return {
            "max_torque": None if self.max_torque is None else list(self.max_torque),
            "thrust_to_weight": self.thrust_to_weight,
            "hover_speed_rad_s": self.hover_speed,
        }

    def describe(self) -> str:
        """One line for a command's output."""
        if self.max_torque is None:
            return (f"vehicle authority: ideal actuators (no rotor speed limit); hover at "
                    f"{self.hover_speed:.4g} rad/s")  # fmt: skip
        roll, pitch, yaw = self.max_torque
        return (
            f"vehicle authority: thrust-to-weight {self.thrust_to_weight:.3g}, largest "
            f"torques roll {roll:.4g}, pitch {pitch:.4g}, yaw {yaw:.4g} N m; hover at "
            f"{self.hover_speed:.4g} rad/s"
        )


def authority(layout: Layout, mass: float, gravity: float, thrust_factor: float,
              drag_factor: float, speed_limit: float | None) -> Authority:  # fmt: skip
    """The :class:`Authority` of ``layout`` with these factors and ``w_max`` =
    ``speed_limit`` (rad/s; ``None``: unlimited)."""
    hover = hover_speeds_squared(layout, mass, gravity, thrust_factor)
    hover_speed = float(math.sqrt(max(0.0, float(np.max(hover)))))
    if speed_limit is None:
        return Authority(None, None, hover_speed)
    top = float(speed_limit) ** 2
    m = layout.allocation(thrust_factor, drag_factor)
    ratio = float(np.sum(m[0]) * top / (mass * gravity))
    torque = tuple(
        float(min(np.sum(np.clip(row, 0.0, None)), np.sum(np.clip(-row, 0.0, None))) * top)
        for row in m[1:]
    )
    return Authority(ratio, torque, hover_speed)


def lag_weights(time_constant: float, dt: float) -> tuple[float, float]:
    """``(decay, mean)`` of the exact first-order lag over one step (module docstring):
    ``q(dt) = q_c + decay (q_k - q_c)`` and the step's mean ``q_c + mean (q_k - q_c)``.
    ``time_constant`` > 0 s."""
    r = dt / time_constant
    return math.exp(-r), -math.expm1(-r) / r
