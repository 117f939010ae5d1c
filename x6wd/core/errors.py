"""One error hierarchy for the whole project; subclasses name the phase that failed."""

import errno


class X6wdError(Exception):
    """Base class of every error x6wd raises on purpose."""


class ConfigError(X6wdError):
    """Invalid configuration: the message names the key and the reason."""


class DeviceUnavailable(X6wdError):
    """A device could not be opened (missing port, no I2C bus, refused connection)."""


class DeviceIOError(X6wdError):
    """A device was open but an I/O operation on it failed."""


class DeviceTimeout(X6wdError):
    """A device did not answer within its deadline."""


class CommandError(X6wdError):
    """An operator request the robot refuses; ``code`` is the control protocol's error code
    ("geofence", "bad_request", "rejected", ...; docs/protocol.md)."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


class ParseError(X6wdError):
    """Bytes or text that do not form a valid message."""


class ProtocolError(X6wdError):
    """A peer broke the remote-control or gpsd protocol."""


# Errno values that mean "try again" on a device (an I2C bus, a UART, a USB adapter being
# re-enumerated), as one class for every driver: EIO (5, bus or line glitch), ENXIO (6, no
# ACK at the address / device gone for a moment), EAGAIN (11), EBUSY (16, bus held by another
# master), EINTR (4), EPROTO (71, USB protocol error), ETIMEDOUT (110) and EREMOTEIO (121,
# I2C NACK). Anything else (ENOENT, EACCES, EBADF ...) is a real fault.
TRANSIENT_ERRNOS: frozenset[int] = frozenset(
    {
        errno.EIO,
        errno.ENXIO,
        errno.EAGAIN,
        errno.EBUSY,
        errno.EINTR,
        errno.EPROTO,
        errno.ETIMEDOUT,
        errno.EREMOTEIO,
    }
)


def is_transient(exc: BaseException) -> bool:
    """True when ``exc`` is an OSError whose errno is in :data:`TRANSIENT_ERRNOS`."""
    return isinstance(exc, OSError) and exc.errno in TRANSIENT_ERRNOS
