"""A real robot's K-Team replies, in either dialect, as the topic messages the simulated robot
publishes (``[real] kteam_dialect``; docs/recording.md "Real drivers" has the table).

The codec (:class:`koala_bridge.drivers.kteam.Dialect`) turns a line into a
:class:`~koala_bridge.drivers.messages.KteamReply` in the robot's units; this module converts
it to SI and to the typed messages of :mod:`koala_bridge.core.topics`:

============  =================  ==================================================================
dialect       reply              message
============  =================  ==================================================================
``koala1``    ``n,<counts>``     ``sensors/ir``: proximity counts (no ambient light: null)
``koala1``    ``h,l,r``          ``sensors/odometry``: encoder pulses, as counted
``koala25``   ``p,l,r``          ``sensors/odometry``: encoder pulses, as counted
``koala25``   ``g,<9 x cm>``     ``sensors/sonar``: m; ``0`` (closer than 25 cm) -> 0.0 m, as the
                                 simulator publishes a range below ``min_range_m``; ``1000``
                                 (nothing in range) and ``2000`` (disabled) -> null (no echo)
``koala25``   ``n,<30 raw>``     ``sensors/gyro``: one message per new sample, oldest first, yaw
                                 rate = z x 0.066 deg/s in rad/s (libkoala ``KOALA_GYRO_DEG_S``)
``koala25``   ``@,x,y,z``        ``sensors/compass``: mGauss / 10 = uT (1 uT = 10 mGauss)
============  =================  ==================================================================

Other read replies of the Koala 2.5 (``e`` speeds, ``m`` accelerometer, ``o`` currents, ``v``
battery, ``y`` motor status) are recorded as bus frames but have no topic: the simulated robot
publishes none for them.

Gyro time stamps: an ``n`` line carries the last 10 samples (the manual: 95 Hz, 10 values every
~105 ms) without their times. The newest is stamped with the time the line was read, each older
one :data:`GYRO_SAMPLE_PERIOD_S` earlier; a sample is published only if its stamp is later than
the last one published (polls overlap when they come faster than 10 samples' worth, and then
nothing is repeated) and not before the start (t >= 0). A line read late shifts its samples
late by the same amount: the stamps are the host's, as for every real reading.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from types import MappingProxyType

from koala_bridge.core.topics import (
    CompassMessage,
    GyroMessage,
    IrMessage,
    OdometryMessage,
    SonarMessage,
    TopicMessage,
    ints,
)
from koala_bridge.drivers.koala25 import (
    GYRO_DEG_S_PER_UNIT,
    SAMPLES,
    SONARS,
    US_DISABLED,
    US_NEAR,
    US_NONE,
)
from koala_bridge.drivers.kteam import Dialect
from koala_bridge.drivers.messages import FrameError, KteamReply

__all__ = [
    "GYRO_SAMPLE_PERIOD_S",
    "MGAUSS_PER_UT",
    "POLLABLE",
    "KteamReplyDecoder",
    "compass_field_ut",
    "ir_message",
    "gyro_yaw_rates",
    "sonar_ranges_m",
]

#: Per dialect, the commands ``[real] kteam_poll`` may ask and the key their reply is published
#: on (None: recorded only, no topic).
POLLABLE: Mapping[str, Mapping[str, str | None]] = MappingProxyType({
    "koala1": MappingProxyType({"N": "sensors/ir", "H": "sensors/odometry"}),
    "koala25": MappingProxyType({
        "P": "sensors/odometry",
        "G": "sensors/sonar",
        "N": "sensors/gyro",
        "&": "sensors/compass",
        "E": None,
        "M": None,
        "O": None,
        "V": None,
        "Y": None,
    }),
})

GYRO_SAMPLE_PERIOD_S = 1.0 / 95.0
"""Time between two Koala 2.5 gyro samples (the manual: 95 Hz)."""
MGAUSS_PER_UT = 10.0
"""1 uT = 10 mGauss (1 G = 100 uT)."""
_SONAR_NEAR_M = 0.0   # what the simulator publishes nearer than min_range_m (sim/sensors/sonar.py)


def sonar_ranges_m(values: Sequence[int]) -> tuple[float | None, ...]:
    """Koala 2.5 ``G`` values (cm) -> ranges in m; None for no echo (``1000``) or a disabled
    sensor (``2000``); 0.0 for an obstacle closer than 25 cm (``0``)."""
    out: list[float | None] = []
    for v in values:
        if v in (US_NONE, US_DISABLED):
            out.append(None)
        elif v == US_NEAR:
            out.append(_SONAR_NEAR_M)
        else:
            out.append(v / 100.0)
    return tuple(out)


def gyro_yaw_rates(values: Sequence[int]) -> tuple[float, ...]:
    """Koala 2.5 ``N`` values (10 samples x, y, z, newest first; 0.066 deg/s per unit) -> the z
    rates in rad/s, **oldest first**."""
    z = [values[3 * i + 2] for i in range(len(values) // 3)]
    return tuple(math.radians(v * GYRO_DEG_S_PER_UNIT) for v in reversed(z))


def compass_field_ut(values: Sequence[int]) -> tuple[float, float, float]:
    """Koala 2.5 ``&`` values x, y, z in mGauss -> uT."""
    x, y, z = values
    return (x / MGAUSS_PER_UT, y / MGAUSS_PER_UT, z / MGAUSS_PER_UT)


class KteamReplyDecoder:
    """One K-Team port's replies -> topic messages, for its dialect. Keeps the time of the last
    gyro sample published (see the module's note on gyro stamps)."""

    def __init__(self, dialect: Dialect) -> None:
        if dialect.name not in POLLABLE:
            raise ValueError(f"no reply mapping for K-Team dialect {dialect.name!r}")
        self.dialect = dialect
        self._last_gyro_t = -math.inf

    def command_of(self, reply: KteamReply) -> str:
        """The command letter ``reply`` answers (``@`` -> ``&`` on the Koala 2.5)."""
        return self.dialect.reply_commands.get(reply.letter, reply.letter.upper())

    def topic_of(self, reply: KteamReply) -> str | None:
        """The key ``reply`` is published on, or None."""
        return POLLABLE[self.dialect.name].get(self.command_of(reply))

    def messages(self, t: float, reply: KteamReply) -> list[TopicMessage]:
        """The messages of one reply read at host time ``t``; [] for a reply without a topic,
        an error reply, or fields that are not what the command's reply carries."""
        if reply.is_error or self.topic_of(reply) is None:
            return []
        try:
            values = reply.ints
        except FrameError:
            return []
        letter = self.command_of(reply)
        if self.dialect.name == "koala1":
            if letter == "N":
                return [ir_message(t, values)]
            return [OdometryMessage(t, values[0], values[1])] if len(values) == 2 else []
        if letter == "P" and len(values) == 2:
            return [OdometryMessage(t, values[0], values[1])]
        if letter == "G" and len(values) == SONARS:
            return [SonarMessage(t, sonar_ranges_m(values))]
        if letter == "&" and len(values) == 3:
            return [CompassMessage(t, *compass_field_ut(values))]
        if letter == "N" and len(values) == 3 * SAMPLES:
            return self._gyro(t, gyro_yaw_rates(values))
        return []

    def _gyro(self, t: float, rates: Sequence[float]) -> list[TopicMessage]:
        n = len(rates)
        out: list[TopicMessage] = []
        for i, rate in enumerate(rates):
            stamp = t - (n - 1 - i) * GYRO_SAMPLE_PERIOD_S
            if stamp >= 0.0 and stamp > self._last_gyro_t:
                out.append(GyroMessage(stamp, rate))
        if out:
            self._last_gyro_t = out[-1].t
        return out


def ir_message(t: float, counts: Sequence[int]) -> IrMessage:
    """``sensors/ir`` of a real robot: proximity counts only. Neither the range frames nor the
    K-Team ``N`` reply carry ambient light, so ``ambient`` is null for every sensor (not
    measured) and there is no ``truth``."""
    return IrMessage(t, ints(counts), (None,) * len(counts))
