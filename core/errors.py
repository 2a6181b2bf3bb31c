"""The project's exceptions. Every bad-input error derives from :class:`InputError`.

Anything else that escapes a command is a bug in calib: the CLI reports it as an "internal error" with
the traceback written to a file (docs/reliability.md).
"""


class InputError(ValueError):
    """Bad user input: the message is one line naming the file and the problem (``<file>: <problem>``)."""


class InputWarning(UserWarning):
    """A suspicious but usable input (an unknown key, a value outside its usual range): one line, like errors."""
