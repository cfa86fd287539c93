"""One module per `semloc` sub-command: ``add_arguments(parser)`` and ``run(args) -> int``.

Modules import their heavy dependencies inside ``run`` so that ``semloc --help`` stays fast.
"""
