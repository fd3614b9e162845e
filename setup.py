"""Package discovery (pyproject.toml holds everything else). ``envs/`` and ``configs/`` sit at the
top of the repository but install as ``l1flow_rl.envs`` and ``l1flow_rl.configs``; setuptools' finder
cannot map directories to other names, so the sub-packages are found here and renamed."""

from setuptools import find_packages, setup

packages = find_packages(include=["l1flow_rl", "l1flow_rl.*"])
packages += ["l1flow_rl." + p for p in find_packages(include=["envs", "envs.*"])]
packages += ["l1flow_rl.configs"]  # YAML only (package data)

setup(packages=packages)
