"""The one error type users see.

Every check at a public boundary raises :class:`GBError` with a message that names the file or
argument at fault, what was expected, and what to do.  The command-line front ends catch it and
print the message alone (no traceback) with a non-zero exit status.
"""


class GBError(Exception):
    """A user-facing error: bad input, unreadable file, impossible request."""
