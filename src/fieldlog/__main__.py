"""``python -m fieldlog``: the same as the ``fieldlog`` command."""
import sys

from fieldlog.tools.cli import main

sys.exit(main())
