"""``python -m clgs.cli``: the ``clgs`` command."""
from clgs.cli import main

main()
