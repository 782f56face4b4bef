"""The base of every error fullview reports to a user as one line (exit code 2), never as a traceback."""


class FullviewError(Exception):
    """A problem with the user's input, files or environment that the message fully explains."""
