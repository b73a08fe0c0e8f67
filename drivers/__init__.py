"""Codecs (bytes <-> typed messages) and transports (move bytes) for the Koala's buses.

- :mod:`koala_bridge.drivers.messages`: the typed messages and the error tree.
- :mod:`koala_bridge.drivers.kteam`: K-Team ASCII serial protocol (robot and controller sides).
- :mod:`koala_bridge.drivers.rangeframes`: binary IR / sonar range frames with CRC-16/CCITT-FALSE.
- :mod:`koala_bridge.drivers.can_codec`: CAN frames described by ``config/koala.dbc`` (cantools).
- :mod:`drivers.mavlink_codec`: MAVLink 2 compass (HEARTBEAT, SCALED_IMU) via pymavlink.
- :mod:`drivers.transports`: pty, TCP, UDP, loopback, socketcand, slcan and python-can backends.

The same decoders read the simulated buses and a real robot's. Nothing here imports :mod:`sim`.
Wire formats: docs/protocols.md.
"""
