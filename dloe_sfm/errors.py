"""The one exception type for bad user input (files, fields, options)."""


class InputError(ValueError):
    """Bad input: the message is one line that names the file / image / field and the problem.

    The command line turns it into ``dloe-sfm: error: <message>`` and exit code 2.
    """
