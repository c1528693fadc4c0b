"""Subcommands of the ``vbusd`` command line, one module each, each exposing ``command``."""
