"""The env's parameters: the drone's physics and its task's arena, one dataclass (no torch).

:class:`DroneParams` is their one home: each field's name, default, meaning and range (its
:class:`Param`). From it follow the env's keyword arguments and checks
(:class:`~drone_torchrl.envs.drone_env.DroneEnv`, ``make_params``), the config schema's ``env.*``
keys with their defaults and the ``--help`` page's lines (:mod:`drone_torchrl.schema`,
:mod:`drone_torchrl.apps.help`) and the fast engine's constants
(:data:`drone_torchrl.kernels.build.ENV_CONSTANTS`, compared with the kernels' own list when they
load). Torch-free, so that a command's ``--help`` can read it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any

# The arena's largest extent (|x_limit|, |z_min|, |z_max|, m): a kilometre. float32 positions there
# still resolve 0.1 mm, far below what a drone moves in one step (dt = 0.02 s); at 1e300 m they are inf.
MAX_ARENA = 1e3
# Upper bounds of the physical parameters. Past them the task stops making sense: a step longer
# than MAX_DT lets a hovering drone cross the 1 m target zone in one or two steps, gravity above
# MAX_GRAVITY (10x Earth's) makes a 300-step episode a free fall, and a floor tolerance above
# MAX_FLOOR_TOLERANCE would let the drone sink a quarter of the domain's height before "FLOOR".
MAX_DT = 0.1
MAX_GRAVITY = 100.0
MAX_FLOOR_TOLERANCE = 1.0
# The drone's size. Mass cancels out of the motion (thrust is a fraction of the weight), but the
# weight m*g and the angular acceleration's 1/(m r) are float32 numbers: at 1e300 kg or 1e-40 kg
# they overflow (a traceback, or episodes that end at their first step). A gram is lighter than
# any drone that flies, ten tonnes heavier than any built; a motor distance of 1 cm to 100 m alike.
MIN_MASS, MAX_MASS = 1e-3, 1e4
MIN_MOTOR_DISTANCE, MAX_MOTOR_DISTANCE = 1e-2, 1e2
# Thrust per motor in weights: 100 is a thrust-to-weight ratio of 200 (racing drones reach 10-20).
MAX_THRUST = 100.0

# How a state exactly on a bound counts. "inclusive" (the paper's text and the default): inside,
# both for the domain (no termination) and for the target zone. "strict" (the paper's public code,
# `-0.6 < x < 0.6` style): outside of both.
BOUNDS_MODES = ("inclusive", "strict")

#: The metadata key of a :class:`DroneParams` field's :class:`Param`.
PARAM = "drone_torchrl.param"

# A bound of a Param: a float (shown as Python writes it), a labelled value ("0", 0.0), or the name of
# an earlier field (its value is the bound).
Bound = float | tuple[str, float] | str


@dataclass(frozen=True)
class Param:
    """What one :class:`DroneParams` field means and allows (checked by ``drone_env.make_params``).

    Attributes:
        doc: its meaning and unit.
        low, high: its bounds (a ``Bound``), ``low_open``/``high_open``: the bound itself excluded.
        optional: ``None`` is allowed too.
        choices: the values a string field allows (the kernels receive the value's index).
        new: came after the first runs; a saved config without it behaved as the default.
    """

    doc: str
    low: Bound | None = None
    high: Bound | None = None
    low_open: bool = False
    high_open: bool = False
    optional: bool = False
    choices: tuple[str, ...] = ()
    new: bool = False

    def describe(self) -> str:
        """Its meaning and range in one line (the ``--help`` page's): ``m/s^2, in (0.0, 100.0]``."""
        if self.choices:
            return f"{self.doc}; {' | '.join(self.choices)}"
        label = lambda b: b if isinstance(b, str) else b[0] if isinstance(b, tuple) else f"{b:g}"  # noqa: E731
        low = f"{'(' if self.low_open else '['}{label(self.low)}"
        high = f"{label(self.high)}{')' if self.high_open else ']'}"
        return f"{self.doc}; in {low}, {high}" + (" or null" if self.optional else "")


def _param(default: Any, doc: str, **rule: Any) -> Any:
    return field(default=default, metadata={PARAM: Param(doc, **rule)})


_ZERO = ("0", 0.0)
_ARENA = (f"{MAX_ARENA:g} m", MAX_ARENA)


@dataclass(frozen=True)
class DroneParams:
    """The drone's physical parameters and its task's arena: the one home of the env's parameters.

    Each field's :class:`Param` (``dataclasses.fields(DroneParams)[i].metadata[PARAM]``) holds its
    meaning and range; from them follow :func:`~drone_torchrl.envs.drone_env.make_params` (the
    checks), :class:`~drone_torchrl.envs.drone_env.DroneEnv`'s keyword arguments, the config
    schema's ``env.*`` keys (their defaults too) and the fast engine's constants
    (:data:`drone_torchrl.kernels.build.ENV_CONSTANTS`). The defaults are the paper's (Table 2.1);
    the arena is the domain, the target zone and how a state on a bound counts (angles in radians).
    """

    mass: float = _param(
        1.0, "kg; no effect on the motion (thrust is a fraction of the weight, as in the paper)",
        low=MIN_MASS, high=MAX_MASS,
    )  # fmt: skip
    motor_distance: float = _param(
        1.0, "m, diagonal motor-to-motor; the lever arm is half of it, I_yy = 2/5 m r^2",
        low=MIN_MOTOR_DISTANCE, high=MAX_MOTOR_DISTANCE,
    )  # fmt: skip
    # Thrust is a fraction of the weight m*g: with g = 0 no motor command could move the drone.
    gravity: float = _param(9.81, "m/s^2", low=0.0, high=MAX_GRAVITY, low_open=True)
    dt: float = _param(0.02, "s, the semi-implicit Euler step (50 Hz)", low=0.0, high=MAX_DT, low_open=True)
    max_thrust: float | None = _param(
        None, "per-motor thrust limit as a fraction of the weight (1.0: thrust-to-weight 2); null: unbounded (the paper)",
        low=0.0, high=MAX_THRUST, low_open=True, optional=True,
    )  # fmt: skip
    floor_tolerance: float = _param(
        0.05, "m below z_min before the floor counts as hit", low=0.0, high=MAX_FLOOR_TOLERANCE
    )
    x_limit: float = _param(
        2.0, "m, the domain is |x| <= x_limit", low=_ZERO, high=_ARENA, low_open=True, new=True
    )
    z_min: float = _param(
        0.0, 'm, the floor ("floor" resets start here)', low=(f"-{MAX_ARENA:g} m", -MAX_ARENA), high=_ARENA,
        new=True,
    )  # fmt: skip
    z_max: float = _param(4.0, "m, the ceiling", low="z_min", high=_ARENA, low_open=True, new=True)
    alpha_limit: float = _param(
        math.pi / 3, "rad, the tilt bound of the domain and the zone (pi/3: 60 deg)",
        low=_ZERO, high=("pi", math.pi), low_open=True, new=True,
    )  # fmt: skip
    zone_x_limit: float = _param(
        0.8, "m, the target zone is |x| <= zone_x_limit", low=_ZERO, high="x_limit", low_open=True,
        new=True,
    )  # fmt: skip
    zone_z_min: float = _param(
        2.2, "m, the bottom of the target zone", low="z_min", high="z_max", high_open=True, new=True
    )
    zone_z_max: float = _param(
        3.2, 'm, the top of the target zone ("air" resets start at the zone\'s centre)',
        low="zone_z_min", high="z_max", low_open=True, new=True,
    )  # fmt: skip
    bounds: str = _param(
        "inclusive", "a state exactly on a bound: inclusive = inside (the paper's text), strict = outside (its code)",
        choices=BOUNDS_MODES, new=True,
    )  # fmt: skip

    @property
    def strict(self) -> bool:
        """Whether a state exactly on a bound is outside (``bounds="strict"``).

        On the domain's bound such a state terminates; on the zone's, it is not in the zone.
        """
        return self.bounds == "strict"

    @property
    def zone_z_centre(self) -> float:
        """The target zone's centre height, where ``reset_mode="air"`` starts."""
        return 0.5 * (self.zone_z_min + self.zone_z_max)

    @property
    def floor(self) -> float:
        """The height below which (or on which, with strict bounds) the floor is hit."""
        return self.z_min - self.floor_tolerance

    @property
    def lever_arm(self) -> float:
        """``r``: half the diagonal motor-to-motor distance."""
        return 0.5 * self.motor_distance

    @property
    def inertia(self) -> float:
        """``I_yy = 2/5 m r^2`` (eq. 2.4, spherical mass distribution)."""
        return 0.4 * self.mass * self.lever_arm**2

    @property
    def arm_over_inertia(self) -> float:
        """``r / I_yy``: the angular acceleration per newton of thrust difference."""
        return self.lever_arm / self.inertia

    @property
    def weight(self) -> float:
        """The drone's weight ``m * g`` in newtons."""
        return self.mass * self.gravity


#: The names of :class:`DroneParams`' fields in order (the env's physics and arena arguments).
PARAM_NAMES = tuple(f.name for f in fields(DroneParams))
