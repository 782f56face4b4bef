"""The base of every error fullview reports to a user as one line (exit code 2), never as a traceback."""


class FullviewError(Exception):
    """A problem with the user's input, files or environment that the message fully explains."""


class NothingLeftError(FullviewError, RuntimeError):
    """Valid input and settings leave a stage nothing to compute (no point survives a bound); the message names the
    settings that decide it, so the user can change them rather than read a later stage's failure."""
