"""The exception tree.

    MagcalError                      base of everything magcal raises on purpose
    ├── ConfigError                  bad config file / environment / option (names the key)
    │   └── PortError                a port string or device option no backend takes (names it)
    ├── InputError                   a recording or CSV that cannot be read (names file and line)
    │   ├── DataInsufficient         read, but too few or degenerate samples for the analysis
    │   ├── NeedsChoice              several of what the command takes one of, none named (--mag)
    │   └── ExtraMissing             reading it needs an optional extra that is not installed
    ├── DeviceError                  the device or its port
    │   ├── PortUnavailable          the port cannot be opened or vanished (unplug)
    │   ├── IdentityError            WHO_AM_I / WIA / protocol version not what we talk to
    │   ├── NoReply                  a command was not acknowledged in time
    │   ├── CommandRefused           the device answered a command with an error code
    │   ├── Unsupported              this device has not the ability asked for (see Abilities)
    │   └── WriteRejected            the device refused or mis-echoed a calibration
    └── StateError                   a persisted state file that is invalid

Fits do not raise for bad data: they return a failure value (see magcal.fit).
"""


class MagcalError(Exception):
    """Base class for errors magcal raises on purpose."""


class ConfigError(MagcalError):
    """``keys``: the settings the problem is about (dotted paths), so the reader of the
    settings can say where each was set (file, environment variable, option)."""

    def __init__(self, message: str, keys: tuple = ()):
        super().__init__(message)
        self.keys = tuple(keys)


class PortError(ConfigError):
    """A port string or device option that no backend takes: unknown, malformed or out of
    range. One type for every backend (``magcal.devices.port`` raises it)."""


class InputError(MagcalError):
    pass


class DataInsufficient(InputError):
    """The recording was read, and its samples cannot support the analysis asked for (too few,
    all at one point): the data did not pass, as a fit that fails says (exit 3, not 6)."""


class NeedsChoice(InputError):
    """The input holds several of what the command takes one of (a flight log's magnetometers),
    and the command line named none: the command line's to say (exit 2); the message lists them."""


class ExtraMissing(InputError):
    """Reading this input needs an optional extra that is not installed (exit 2, as the missing
    extra of any command; the message names the pip command)."""


class DeviceError(MagcalError):
    pass


class PortUnavailable(DeviceError):
    pass


class IdentityError(DeviceError):
    pass


class NoReply(DeviceError):
    pass


class CommandRefused(DeviceError):
    """The device answered ``command`` with the error ``code`` (``RANGE``, ``UNKNOWN`` …)."""

    def __init__(self, message: str, command: str = "", code: str = ""):
        super().__init__(message)
        self.command = command
        self.code = code


class Unsupported(DeviceError):
    pass


class WriteRejected(DeviceError):
    pass


class StateError(MagcalError):
    pass
