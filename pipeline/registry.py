"""Stage lookup by name from a mapping name -> "module:Class" (the app passes `stages.STAGES`)."""
from __future__ import annotations

import importlib
from collections.abc import Mapping

from pipeline.errors import UserError
from pipeline.stage import Stage


class UnknownStageError(UserError):
    pass


def load_ref(ref: str) -> type[Stage]:
    module_name, _, class_name = ref.partition(":")
    module = importlib.import_module(module_name)
    cls = getattr(module, class_name, None)
    if not (isinstance(cls, type) and issubclass(cls, Stage)):
        raise TypeError(f"stage reference '{ref}' does not name a Stage subclass")
    return cls


def load_stage(registry: Mapping[str, str], name: str) -> type[Stage]:
    if name not in registry:
        raise UnknownStageError(f"unknown stage '{name}'; known stages are: {', '.join(sorted(registry))}.")
    cls = load_ref(registry[name])
    if cls.name != name:
        raise TypeError(f"registry entry '{name}' -> {registry[name]} declares name '{cls.name}'")
    return cls
