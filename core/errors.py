"""The project's exceptions. Every bad-input error derives from :class:`InputError`."""


class InputError(ValueError):
    """Bad user input: the message is one line naming the file and the problem (``<file>: <problem>``)."""
