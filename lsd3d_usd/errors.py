"""Errors that reach the user as one clear line (the CLI prints them without a traceback)."""


class Lsd3dError(Exception):
    """A user-facing error: the message names what is wrong and where."""


class InputError(Lsd3dError):
    """Bad input: missing, unreadable or malformed files, invalid values."""


def excerpt(value, limit: int = 60) -> str:
    """A short, printable quote of untrusted input for an error message (repr, cut to
    ``limit`` characters), so a bad line of a file is named without echoing kilobytes."""
    if isinstance(value, (bytes, bytearray)):
        value = bytes(value[:limit + 1]).decode("latin-1")
    text = repr(str(value)[:limit + 1])
    if len(str(value)) > limit:
        text = text[:-1][:limit + 1] + "...'"
    return text
