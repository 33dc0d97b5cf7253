"""Deployment files shipped with the package: launch profiles (``profiles/*.toml``), Zenoh router
and client configs (``zenoh/``), systemd unit templates (``systemd/``) and an example parameter
file. Read them with :func:`importlib.resources.files` on ``topoexplore.deploy``."""
