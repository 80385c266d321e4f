"""``python -m clgs``: the same as the ``clgs`` command."""
from clgs.cli import main

main(prog_name="clgs")
