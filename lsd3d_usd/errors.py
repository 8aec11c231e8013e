"""Errors that reach the user as one clear line (the CLI prints them without a traceback)."""


class Lsd3dError(Exception):
    """A user-facing error: the message names what is wrong and where."""


class InputError(Lsd3dError):
    """Bad input: missing, unreadable or malformed files, invalid values."""
