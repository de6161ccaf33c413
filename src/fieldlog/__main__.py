"""``python -m fieldlog``: the same as the ``fieldlog`` command."""
from fieldlog.tools.cli import run

run()
