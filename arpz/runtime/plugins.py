"""A team's own classes named in a config: ``"mylab.dock:DockPlanner"`` -> the class.

Drivers, planners and actuators are all named this way (docs/nodes.md). Loading happens at
start-up, so a wrong name stops the process before it joins the fleet, with an error that says
which setting, which module or attribute, and what the class must be.
"""

from __future__ import annotations

import importlib
from typing import TypeVar

from arpz.core.errors import ConfigError

T = TypeVar("T")


class PluginError(ConfigError):
    """A class named in a config that cannot be loaded, or is not what the setting needs."""


def load_class(spec: str, base: type[T], *, setting: str) -> type[T]:
    """The class ``spec`` (``module.path:ClassName``) names, checked to subclass ``base``."""
    module_name, sep, class_name = spec.partition(":")
    if not sep or not module_name or not class_name:
        raise PluginError(f"{setting}: write 'module.path:ClassName', got {spec!r}")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise PluginError(
            f"{setting}: cannot import module {module_name!r} ({exc}); install it, or run from "
            "the folder that holds it, or add that folder to PYTHONPATH"
        ) from None
    cls = getattr(module, class_name, None)
    if cls is None:
        raise PluginError(f"{setting}: module {module_name!r} has no {class_name!r}")
    if not (isinstance(cls, type) and issubclass(cls, base)):
        raise PluginError(
            f"{setting}: {spec!r} is not a subclass of {base.__module__}.{base.__qualname__}"
        )
    return cls
