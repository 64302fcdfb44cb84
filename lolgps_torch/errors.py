"""User-facing errors: scripts print ``error: <message>`` on one line and exit with status 2."""


class LolgpsError(Exception):
    """Bad input or an unrecoverable numerical failure, with a message a user can act on."""


class NumericalError(LolgpsError):
    """A numerical failure while learning one condition (a C-step with no positive-definite
    Quu, non-finite dynamics, a simulator that blew up): the stream reports the condition as
    failed and goes on with the next one."""
