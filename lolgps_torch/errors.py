"""User-facing errors: scripts print ``error: <message>`` on one line and exit with status 2."""


class LolgpsError(Exception):
    """Bad input or an unrecoverable numerical failure, with a message a user can act on."""
