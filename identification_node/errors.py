"""Errors raised for user mistakes: the CLI prints them without a traceback."""


class IdentificationError(ValueError):
    """A user mistake (bad robot, joint, sample, parameter or file), with a readable message."""
