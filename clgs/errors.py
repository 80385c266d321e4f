"""The one base of the errors clgs raises about what it was given (a file, a setting, a mesh, a
plugin): the command line shows their message instead of a traceback (:mod:`clgs.cli`).

Each subclass is also the built-in exception its kind of mistake has always been (most are
``ValueError``), so ``except ValueError`` keeps working. Imports nothing."""


class ClgsError(Exception):
    """Something clgs was given cannot be used; the message says what and what to do."""


class InputError(ClgsError, ValueError):
    """A value clgs was given is out of range or of the wrong kind (a setting, an array's shape, a
    size): what ``ValueError`` says, as a :class:`ClgsError`."""
