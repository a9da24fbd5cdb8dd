"""The exception tree.

    MagcalError                      base of everything magcal raises on purpose
    ├── ConfigError                  bad config file / environment / option (names the key)
    ├── InputError                   a recording or CSV that cannot be read (names file and line)
    ├── DeviceError                  the device or its port
    │   ├── PortUnavailable          the port cannot be opened or vanished (unplug)
    │   ├── IdentityError            WHO_AM_I / WIA / protocol version not what we talk to
    │   ├── NoReply                  a command was not acknowledged in time
    │   └── WriteRejected            the device refused or mis-echoed a calibration
    └── StateError                   a persisted state file that is invalid

Fits do not raise for bad data: they return a failure value (see magcal.fit).
"""


class MagcalError(Exception):
    """Base class for errors magcal raises on purpose."""


class ConfigError(MagcalError):
    pass


class InputError(MagcalError):
    pass


class DeviceError(MagcalError):
    pass


class PortUnavailable(DeviceError):
    pass


class IdentityError(DeviceError):
    pass


class NoReply(DeviceError):
    pass


class WriteRejected(DeviceError):
    pass


class StateError(MagcalError):
    pass
