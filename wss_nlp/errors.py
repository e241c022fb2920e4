"""Exception types. Every message names the file or item and what to do."""


class WssNlpError(Exception):
    """Base class of all errors raised on purpose by wss-nlp."""

    exit_code = 1


class InputError(WssNlpError):
    """Bad input data or options (missing item, NaN, wrong shape, ...)."""

    exit_code = 2


class NoVesselError(InputError):
    """No lumen could be found in the field of view."""


class LumenTouchesBorderError(InputError):
    """The lumen is cut by the border of the field of view."""


class NoiseEstimationError(InputError):
    """The data do not allow a noise estimate; the message names the option that supplies one."""


class SolverError(WssNlpError):
    """A numerical solver failed and returned nothing usable."""

    exit_code = 1
