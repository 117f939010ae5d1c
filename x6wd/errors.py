"""One error hierarchy for the whole project; subclasses name the phase that failed."""


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


class ParseError(X6wdError):
    """Bytes or text that do not form a valid message."""


class ProtocolError(X6wdError):
    """A peer broke the remote-control or gpsd protocol."""
