"""The built-in dataflow graphs and the files they read, installed as the package ``semloc_deploy`` (setup.py):
``semloc up NAME`` finds ``NAME.yaml`` here (services/launcher.py ``find_graph``). No code."""
