"""Controllers by name, so that command lines, studies and the tuner can pick them.

A control law registers itself with :func:`register` (a class decorator). A law
defined outside this package is reached by ``"package.module:Class"`` (imported on
first use, then registered under its ``name``) or through the entry-point group
``fojax.controllers`` of an installed package (``name = "package.module:Class"``).
"""

from __future__ import annotations

import dataclasses
import difflib
import importlib
from importlib import metadata
from typing import Any

__all__ = [
    "PAPER_CONTROLLERS",
    "controller_names",
    "controller_options",
    "get_controller_class",
    "make_controller",
    "register",
]

ENTRY_POINT_GROUP = "fojax.controllers"
PAPER_CONTROLLERS = ("afonftsmc", "anftsmc", "fobsmc", "bsmc", "fl")
"""The paper's controller and the four it is compared with (Section V), in order."""
_LAWS: dict[str, type] = {}


def register(cls: type) -> type:
    """Register a :class:`fojax.controllers.ControlLaw` subclass under ``cls.name``."""
    from fojax.controllers.base import ControlLaw
    from fojax.controllers.gains import GainSpec

    if not (isinstance(cls, type) and issubclass(cls, ControlLaw)):
        raise TypeError(f"{cls!r} is not a subclass of fojax.controllers.ControlLaw")
    if not dataclasses.is_dataclass(cls) or not cls.__dataclass_params__.frozen:
        raise TypeError(f"control law {cls.__name__} must be a frozen dataclass")
    name = getattr(cls, "name", None)
    if not isinstance(name, str) or not name:
        raise TypeError(f"control law {cls.__name__} needs a class attribute 'name'")
    if not isinstance(getattr(cls, "GAINS", None), GainSpec):
        raise TypeError(f"control law {cls.__name__} needs a class attribute 'GAINS' (GainSpec)")
    _LAWS[name] = cls
    return cls


def _builtin() -> None:
    import fojax.controllers  # noqa: F401  (its modules register the built-in laws)


def controller_names() -> tuple[str, ...]:
    """Names of the registered controllers: the paper's AFONFTSMC first, then the four
    it is compared with (ANFTSMC, FOBSMC, BSMC, FL), then any registered later."""
    _builtin()
    return tuple(_LAWS)


def _load(spec: str) -> type:
    module_name, _, attribute = spec.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as error:
        raise ValueError(
            f"cannot import {module_name!r} for controller {spec!r}: {error}"
        ) from None
    cls = getattr(module, attribute, None)
    if cls is None:
        raise ValueError(f"module {module_name!r} has no {attribute!r} (controller {spec!r})")
    try:
        return register(cls)
    except TypeError as error:
        raise ValueError(f"{spec}: {error}") from None


def get_controller_class(name: str) -> type:
    """The law class registered as ``name``, or ``"package.module:Class"`` loaded;
    ``ValueError`` listing the choices otherwise."""
    _builtin()
    if not isinstance(name, str):
        raise TypeError(f"a controller name must be a string, got {type(name).__name__}")
    if name in _LAWS:
        return _LAWS[name]
    if ":" in name:
        return _load(name)
    for entry in metadata.entry_points(group=ENTRY_POINT_GROUP):
        if entry.name == name:
            return _load(entry.value)
    close = difflib.get_close_matches(name, _LAWS, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    raise ValueError(
        f"unknown controller {name!r}{hint}; choose one of {', '.join(_LAWS)}, or give "
        "'package.module:Class' for a control law of your own"
    )


def _fields(cls: type) -> set[str]:
    return {f.name for f in dataclasses.fields(cls) if f.init}


def controller_options(name: str) -> set[str]:
    """The configuration options ``name`` accepts (its law's and the cascade's)."""
    from fojax.controllers.cascade import Cascade

    return _fields(get_controller_class(name)) | (_fields(Cascade) - {"law"})


def make_controller(name: str, **options: Any):
    """Controller ``name`` (a :class:`fojax.controllers.Cascade` around its law) with
    the configuration ``options``.

    Options are the law's fields (``dt``, ``horizon``, ``switching``,
    ``fractional_method``, ...) and the cascade's (``filter_frequency``,
    ``filter_damping``, ``thrust_floor``); ``None`` leaves the default. An option that
    no registered controller has raises ``TypeError``; one that only other controllers
    have (``switching`` for FL, which has no switching function) is ignored, so one set
    of options configures every controller.
    """
    from fojax.controllers.cascade import Cascade

    cls = get_controller_class(name)
    own = _fields(cls)
    cascade = _fields(Cascade) - {"law"}
    known = set(cascade).union(*(_fields(c) for c in _LAWS.values()))
    unknown = sorted(set(options) - known)
    if unknown:
        hints = [difflib.get_close_matches(u, known, n=1) for u in unknown]
        text = ", ".join(
            f"{u!r}" + (f" (did you mean {h[0]!r}?)" if h else "")
            for u, h in zip(unknown, hints, strict=True)
        )
        raise TypeError(
            f"unknown controller option(s) {text}; {name} accepts "
            f"{', '.join(sorted(own | cascade))}"
        )
    law = cls(**{k: v for k, v in options.items() if k in own and v is not None})
    return Cascade(law, **{k: v for k, v in options.items() if k in cascade and v is not None})
