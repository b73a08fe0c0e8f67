"""The project's one error tree, rooted at :class:`KoalaBridgeError`.

Every exception koala-bridge raises on purpose is a :class:`KoalaBridgeError`; the command line
(``cli/main.py``) catches it once and prints one line, ``koala-bridge <subcommand>: <message>``,
exit 2. A foreign error (OSError, a library's own) that means "this input cannot be used" is
wrapped where it crosses into the project, ``raise RecordingError(...) from e``, so the message
is the project's and the cause stays in the traceback for ``--log-level DEBUG`` readers.

A bad frame on a live bus is a value (counted, logged, answered), never one of these: the
exceptions are for a configuration, a file or a request that has no answer.

::

    KoalaBridgeError
    ├── ConfigError (ValueError)        a config key or value is invalid (core.schema)
    ├── TopicError (ValueError)         a payload does not have its topic's shape (core.topics)
    ├── DriverError                     codecs and transports (drivers.messages)
    │   ├── FrameError (ValueError)     a value cannot be encoded in / decoded from a wire format
    │   └── TransportError (OSError)    a transport cannot be opened or fails moving bytes
    │       ├── TransportClosedError    used after close()
    │       └── BusOpenError            a configured bus cannot be opened (runtime.buses)
    ├── RecordingError                  an MCAP recording cannot be written or read
    │   └── UnsupportedRecordingError   valid MCAP this version cannot use
    ├── EstimationError (ValueError)    an estimation input has no answer (estimation.errors)
    │   └── DegenerateGeometryError     e.g. collinear landmarks
    └── CalibrationError                calibration.errors
        ├── BundleError                 a measurement bundle is missing or unreadable
        ├── ModelConfigError            the model TOML cannot be read
        └── EffectRegistryError         an effect name registered twice or unknown

The classes are defined here once; the modules named above re-export them under the names
they always had (``from koala_bridge.core.schema import ConfigError`` keeps working). The
mixin bases (``ValueError``, ``OSError``) are kept where callers catch those.
"""

from __future__ import annotations

__all__ = [
    "CalibrationError",
    "ConfigError",
    "DriverError",
    "EstimationError",
    "FrameError",
    "KoalaBridgeError",
    "RecordingError",
    "TopicError",
    "TransportClosedError",
    "TransportError",
]


class KoalaBridgeError(Exception):
    """Root of every exception koala-bridge raises on purpose; the CLI catches it once."""


class ConfigError(KoalaBridgeError, ValueError):
    """A configuration value or key is invalid. The message names the section and the key."""


class TopicError(KoalaBridgeError, ValueError):
    """A payload does not have the shape of its topic's message (:mod:`.topics`)."""


class DriverError(KoalaBridgeError):
    """Root of every exception raised by :mod:`koala_bridge.drivers`."""


class FrameError(DriverError, ValueError):
    """A value cannot be encoded in (or was wrongly decoded from) a wire format."""


class TransportError(DriverError, OSError):
    """A transport could not be opened or failed while moving bytes."""


class TransportClosedError(TransportError):
    """An operation was attempted on a transport after ``close()``."""


class RecordingError(KoalaBridgeError):
    """A recording cannot be written or read."""


class EstimationError(KoalaBridgeError, ValueError):
    """Root of every exception raised by :mod:`koala_bridge.estimation`."""


class CalibrationError(KoalaBridgeError):
    """Root of every exception raised by :mod:`koala_bridge.calibration`."""
