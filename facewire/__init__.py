"""The ``facewire`` command: argument parsing and dispatch only (see ``cli.py``)."""
