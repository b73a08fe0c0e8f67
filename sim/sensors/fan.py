"""Ray fans of range sensors: body-frame sensor poses x rays per sensor -> world-frame rays."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from koala_bridge.sim.sensors.base import fan_offsets


@dataclass(frozen=True)
class RayFan:
    """``n`` sensors at body poses ``(n, 3)`` ``[x, y, theta]``, ``k`` rays each over an aperture.

    Rays are ordered sensor-major: ray ``i * k + j`` is ray ``j`` of sensor ``i``; ray ``k // 2``
    of each sensor lies on its axis (``k`` is odd).
    """

    bx: np.ndarray      # (n*k,) body-frame ray origins
    by: np.ndarray
    ba: np.ndarray      # (n*k,) body-frame ray angles
    n: int
    k: int
    body: np.ndarray = field(init=False, repr=False)  # (3, n*k) rows bx, by, ba (C-contiguous)

    def __post_init__(self) -> None:
        object.__setattr__(self, "body", np.ascontiguousarray(np.stack([self.bx, self.by,
                                                                         self.ba])))

    @classmethod
    def build(cls, poses: np.ndarray, rays: int, aperture_rad: float) -> RayFan:
        off = fan_offsets(rays, aperture_rad)
        bx = np.repeat(poses[:, 0], rays)
        by = np.repeat(poses[:, 1], rays)
        ba = (poses[:, 2][:, None] + off[None, :]).reshape(-1)
        return cls(bx, by, ba, int(poses.shape[0]), int(rays))

    @staticmethod
    def concat(fans: list[RayFan]) -> RayFan:
        """Several fans as one (for a single transform and cast); ``n``/``k`` of the first."""
        if len(fans) == 1:
            return fans[0]
        return RayFan(np.concatenate([f.bx for f in fans]), np.concatenate([f.by for f in fans]),
                      np.concatenate([f.ba for f in fans]), fans[0].n, fans[0].k)

    def world_rays(
        self, x: float, y: float, theta: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """World-frame ``(ox, oy, dx, dy)``, each ``(n*k,)``, for a robot at ``(x, y, theta)``."""
        c = math.cos(theta)
        s = math.sin(theta)
        ox = x + c * self.bx - s * self.by
        oy = y + s * self.bx + c * self.by
        a = self.ba + theta
        return ox, oy, np.cos(a), np.sin(a)

    @property
    def size(self) -> int:
        return int(self.bx.shape[0])
