"""The errors arpz raises on purpose, under one base so callers can catch arpz's and nothing else.

Kept at the bottom of the layers (no imports): any module may raise them.
"""

from __future__ import annotations


class ArpzError(Exception):
    """Base of every error arpz raises on purpose."""


class ConfigError(ArpzError, ValueError):
    """A configuration that cannot be used; ``str()`` names the file, the field and the problem."""
