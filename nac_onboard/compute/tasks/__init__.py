"""The compute tasks: every module here defines one Task subclass; adding a task is adding a module."""

from __future__ import annotations

import importlib
import pkgutil

from nac_onboard.compute.task import Task


def all_tasks() -> dict[str, type[Task]]:
    """Task classes by name, from every module of this package."""
    found = {}
    for module in pkgutil.iter_modules(__path__):
        loaded = importlib.import_module(f"{__name__}.{module.name}")
        for value in vars(loaded).values():
            if isinstance(value, type) and issubclass(value, Task) and value is not Task and value.__module__ == \
                    loaded.__name__:
                found[value.name] = value
    return dict(sorted(found.items()))
