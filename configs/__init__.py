"""The shipped configuration files (scanner hardware, protocols, phantoms, backends,
registration settings), as package data: :data:`CONFIGS` finds them in a checkout and in an
installed wheel alike."""

from pathlib import Path

CONFIGS = Path(__file__).resolve().parent
"""The folder of the shipped configs: the defaults of every command's config options."""
