"""Several simulated Koalas in one world: ``reset(seed) -> [Readings]``,
``step(commands) -> [Readings]``, nothing else.

Each robot is a :class:`sim.simulator.Simulator` of its own configuration (its own start pose,
sensors and error models) in the same world and with the same ``dt``. The others' bodies are
obstacles to each (:meth:`Simulator.share_bodies`: seen by IR, sonar and camera, and stopping a
robot on contact as a wall does).

A step moves the robots one after the other in their order, each against the others where they
are at that moment (a robot never moves into a body that has just moved), then takes every
robot's readings with all of them at their new poses: the readings of step ``k`` see the world
at ``t = k dt``.

Randomness: robot ``i`` draws from ``SeedSequence(seed, spawn_key=(key_i,))`` -- the
``key_i``-th child of ``SeedSequence(seed)`` -- where ``key_i`` is its stream key (by default its
index). The same seed gives every robot the same streams, bit for bit, and no robot's draws depend
on another's.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from koala_bridge.sim.simulator import Simulator
from koala_bridge.sim.types import Readings, WheelCommand


class Fleet:
    """The robots of one world, stepped together (module docstring)."""

    def __init__(self, simulators: Sequence[Simulator],
                 stream_keys: Sequence[int] | None = None) -> None:
        if not simulators:
            raise ValueError("a fleet needs at least one robot")
        dts = {s.dt for s in simulators}
        if len(dts) != 1:
            raise ValueError(f"every robot of a fleet steps with the same dt, got {sorted(dts)}")
        keys = list(range(len(simulators))) if stream_keys is None else list(stream_keys)
        if len(keys) != len(simulators) or len(set(keys)) != len(keys):
            raise ValueError(f"stream keys must be one distinct key per robot, got {keys}")
        self.robots = list(simulators)
        self.stream_keys = keys
        self.dt = simulators[0].dt
        # Every body, rows x, y, radius, shared with each robot (Simulator.share_bodies) and
        # moved in place as the robots move.
        self._bodies = np.zeros((len(simulators), 3))
        self._bodies[:, 2] = [s.config.robot.body_radius_m for s in simulators]
        for i, sim in enumerate(self.robots):
            sim.share_bodies(self._bodies, i)

    def __len__(self) -> int:
        return len(self.robots)

    @property
    def t(self) -> float:
        """Simulation time of the last step, s."""
        return self.robots[0].t

    @property
    def step_count(self) -> int:
        return self.robots[0].step_count

    def reset(self, seed: int | None = None) -> list[Readings]:
        """Every robot at its start pose, reseeded; their step-0 readings."""
        seed = self.robots[0].config.sim.seed if seed is None else seed
        self._bodies[:, :2] = [_start(s) for s in self.robots]
        return [sim.reset(seed, spawn_key=(key,))
                for sim, key in zip(self.robots, self.stream_keys, strict=True)]

    def step(self, commands: Sequence[WheelCommand]) -> list[Readings]:
        """Advance every robot one step with its command; their readings (module docstring)."""
        if len(commands) != len(self.robots):
            raise ValueError(f"{len(self.robots)} robots need as many commands, "
                             f"got {len(commands)}")
        bodies = self._bodies
        for i, sim in enumerate(self.robots):      # where each is now (faults may teleport)
            p = sim.pose
            bodies[i, 0], bodies[i, 1] = p.x, p.y
        for i, (sim, command) in enumerate(zip(self.robots, commands, strict=True)):
            sim.move(command)
            p = sim.pose
            bodies[i, 0], bodies[i, 1] = p.x, p.y
        return [sim.sense() for sim in self.robots]


def _start(sim: Simulator) -> tuple[float, float]:
    start = sim.world.start
    if start is None:
        return sim.world.cell_centre(*sim.world.free_cells()[0])
    return (start.x, start.y)
