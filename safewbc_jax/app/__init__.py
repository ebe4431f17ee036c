"""The ``safewbc`` command and its runs."""
