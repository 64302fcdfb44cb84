"""User-facing errors: scripts print ``error: <message>`` on one line and exit with status 2."""


class LolgpsError(Exception):
    """Bad input or an unrecoverable numerical failure, with a message a user can act on."""


class NumericalError(LolgpsError):
    """A numerical failure while learning one condition (a C-step with no positive-definite
    Quu, non-finite dynamics, a simulator that blew up): the stream reports the condition as
    failed and goes on with the next one."""


def check_fields(owner: object, checks: dict[str, bool]) -> None:
    """Raise a :class:`LolgpsError` naming the first field of ``owner`` whose check failed
    (a config's ``__post_init__`` passes ``{field name: its value is valid}``)."""
    for name, ok in checks.items():
        if not ok:
            kind = type(owner).__name__
            raise LolgpsError(f"{kind}.{name} = {getattr(owner, name)!r}: out of range")
