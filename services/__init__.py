"""semloc services: the worker processes, their shared runtime, the launcher and the command line."""
