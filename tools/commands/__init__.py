"""The ``fieldlog`` commands: one module each, with its parser (``add_parser(subparsers)``) beside its code
(``run(args) -> exit code``); ``common`` holds what they share. ``COMMANDS``: the modules in ``--help`` order."""
from fieldlog.tools.commands import (acquire, allan, batch, demo, evaluate, export, filter, fuse, import_, info,
                                     rebuild, recover, replay, report, sim, study, view)

COMMANDS = (sim, acquire, recover, info, filter, import_, rebuild, allan, fuse, evaluate, view, report, export, batch,
            replay, study, demo)
