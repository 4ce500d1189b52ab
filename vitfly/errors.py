"""The one exception type the command line turns into a single error line."""


class VitflyError(Exception):
    """Bad input or a failed precondition, with a message that says what to fix.

    Raise it where the bad input enters (name the file, the field and what was expected);
    ``vitfly.cli`` prints ``vitfly: error: <message>`` and exits with status 2.
    """
