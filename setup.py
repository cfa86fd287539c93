"""The packages of the distribution (everything else is in pyproject.toml): the code's, and deploy/ installed as the
package ``semloc_deploy`` - the built-in graphs and the files they read, which `semloc up local` and `semloc demo`
find by name from any directory (services/launcher.py ``find_graph``). A pyproject table cannot both find packages
and map a folder to another package name. Folders of data count as (namespace) packages, so that their files are
package data (setuptools warns about folders missing from ``packages``)."""

from setuptools import find_namespace_packages, setup

CODE = find_namespace_packages(include=["semloc_core*", "schemas*", "services*"], exclude=["*.__pycache__"])
DEPLOY = ["semloc_deploy"] + [f"semloc_deploy.{name}" for name in find_namespace_packages(where="deploy")
                              if "__pycache__" not in name]
setup(packages=CODE + DEPLOY, package_dir={"semloc_deploy": "deploy"})
