"""Plug-in modules for motiond, each registered under the ``motiond.modules`` entry point group."""
