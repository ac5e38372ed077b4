"""Vehicle subclasses whose per-tick kinematics run on Python floats (``av_gym.sim.fmath``) instead of numpy
scalars: the same operations in the same order as highway-env's ``Vehicle.step``, so the same bits.

Why: ``Vehicle.step`` builds a 2-element array and calls four numpy ufuncs on single floats per vehicle per tick;
the dispatch overhead (~1 µs a call) is most of its cost. The models (kinematic bicycle, IDM, MOBIL, the lateral
controller) are highway-env's: these classes only override *how* ``step`` is evaluated, plus, for IDM vehicles,
the prediction used by the intersection's regulation (see :class:`FastIDMVehicle`).
"""

from __future__ import annotations

from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import MDPVehicle
from highway_env.vehicle.kinematics import Vehicle

from av_gym.sim import fmath


def kinematic_step(vehicle: Vehicle, dt: float) -> None:
    """``highway_env.vehicle.kinematics.Vehicle.step`` (modified bicycle model), float by float."""
    vehicle.clip_actions()
    action = vehicle.action
    beta = fmath.atan(1 / 2 * fmath.tan(action["steering"]))
    speed = vehicle.speed
    angle = vehicle.heading + beta
    position = vehicle.position  # updated in place, as the stock ``self.position += v * dt``
    position[0] = position[0] + speed * fmath.cos(angle) * dt
    position[1] = position[1] + speed * fmath.sin(angle) * dt
    if vehicle.impact is not None:
        position += vehicle.impact
        vehicle.crashed = True
        vehicle.impact = None
    vehicle.heading += speed * fmath.sin(beta) / (vehicle.LENGTH / 2) * dt
    vehicle.speed += action["acceleration"] * dt
    vehicle.on_state_update()


class FastVehicle(Vehicle):
    """``Vehicle`` with :func:`kinematic_step` (e.g. the CCFtap target)."""

    def step(self, dt: float) -> None:
        kinematic_step(self, dt)


class FastMDPVehicle(MDPVehicle):
    """``MDPVehicle`` (the discrete-action ego) with :func:`kinematic_step`."""

    def step(self, dt: float) -> None:
        kinematic_step(self, dt)


class FastIDMVehicle(IDMVehicle):
    """``IDMVehicle`` with :func:`kinematic_step`."""

    def step(self, dt: float) -> None:
        self.timer += dt
        kinematic_step(self, dt)
