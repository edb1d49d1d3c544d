"""The one exception type for bad user input; the CLI turns it into a one-line message and exit code 2."""


class InputError(Exception):
    """Bad input from the user: the message names the file, the row or key, and the problem.

    Raised anywhere in the library; only the CLI catches it (prints ``batgraph: error: <message>``
    on one line and exits with code 2, no traceback).
    """
