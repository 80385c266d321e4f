"""Click commands of the ``clgs`` CLI, one module per topic, imported lazily by ``clgs.cli``."""
