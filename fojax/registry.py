"""Controllers by name, so that command lines, studies and the tuner can pick them.

Every registered controller is a frozen dataclass implementing the protocol of
:mod:`fojax.controller` plus ``name``, ``gains_type`` (the NamedTuple of its gains),
``default_gains(dtype)`` and ``check_gains(gains)``. Its configuration fields (for
instance ``dt``, ``horizon``, ``switching``, ``fractional_method``) are filled by
:func:`make_controller`; options a controller does not have are ignored, so one
command line can configure several controllers at once.

User-written controllers register with :func:`register`.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from fojax.afonftsmc import AFONFTSMC
from fojax.anftsmc import ANFTSMC
from fojax.backstepping import BSMC, FOBSMC
from fojax.fl import FL

__all__ = ["controller_names", "get_controller_class", "make_controller", "register"]

_CONTROLLERS: dict[str, type] = {}


def register(cls: type) -> type:
    """Register a controller class under ``cls.name`` (usable as a decorator)."""
    for attribute in ("name", "gains_type", "default_gains", "check_gains", "prepare", "step"):
        if not hasattr(cls, attribute):
            raise TypeError(f"controller class {cls.__name__} has no {attribute!r}")
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"controller class {cls.__name__} must be a (frozen) dataclass")
    _CONTROLLERS[cls.name] = cls
    return cls


register(AFONFTSMC)
# The paper's compared controllers (Section V), in the order of docs/model.md.
register(ANFTSMC)
register(FOBSMC)
register(BSMC)
register(FL)


def controller_names() -> tuple[str, ...]:
    """Names of the registered controllers, in registration order."""
    return tuple(_CONTROLLERS)


def get_controller_class(name: str) -> type:
    """The class registered as ``name``; ``ValueError`` listing the choices otherwise."""
    try:
        return _CONTROLLERS[name]
    except KeyError:
        raise ValueError(
            f"unknown controller {name!r}; choose one of {', '.join(controller_names())}"
        ) from None


def make_controller(name: str, **options: Any):
    """Build controller ``name`` with the configuration ``options`` it accepts.

    Options that are not fields of the controller's dataclass are ignored (for
    instance ``fractional_method`` for a controller without fractional memory);
    ``None`` values are ignored too (the controller's default applies).
    """
    cls = get_controller_class(name)
    fields = {f.name for f in dataclasses.fields(cls) if f.init}
    accepted = {k: v for k, v in options.items() if k in fields and v is not None}
    return cls(**accepted)
