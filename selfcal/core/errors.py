"""The errors a user can cause (bad input, data that cannot determine the model).

Every such error subclasses :class:`SelfcalError`, whichever layer raises it, so the command line catches them
all without importing the layers that define them (``selfcal --help`` stays light): it prints one line and
exits 1.  Anything else is a bug and keeps its traceback.
"""


class SelfcalError(ValueError):
    """Bad input or data that cannot determine the model: reported in one line, never as a traceback."""


USER_ERRORS = (SelfcalError, FileNotFoundError, FileExistsError, NotADirectoryError, PermissionError)
