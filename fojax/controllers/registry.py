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
from collections.abc import Mapping, Sequence
from importlib import metadata
from typing import Any

__all__ = [
    "PAPER_CONTROLLERS",
    "applied_options",
    "controller_names",
    "controller_options",
    "get_controller_class",
    "make_controller",
    "options_for",
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


BUILTIN_MODULES = (
    "fojax.controllers.afonftsmc",
    "fojax.controllers.anftsmc",
    "fojax.controllers.backstepping",
    "fojax.controllers.fl",
)
"""The modules of the built-in laws, each registering its own (:func:`register`): loaded
by name, as a law of one's own is, so that this module imports none of them."""


def _builtin() -> None:
    for name in BUILTIN_MODULES:
        importlib.import_module(name)


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


def _cascade_options() -> set[str]:
    from fojax.controllers.cascade import Cascade

    return _fields(Cascade) - {"law"}


def controller_options(name: str) -> set[str]:
    """The configuration options controller ``name`` takes: its law's fields (``dt``,
    ``horizon``, and e.g. ``switching``, ``fractional_method``) and the cascade's
    (``filter_frequency``, ``filter_damping``, ``thrust_floor``)."""
    return _fields(get_controller_class(name)) | _cascade_options()


def _known_options() -> set[str]:
    """Every option some registered controller takes."""
    _builtin()
    return _cascade_options().union(*(_fields(c) for c in _LAWS.values()))


def _unknown(name: str, options) -> None:
    """``TypeError`` for options no registered controller takes (a typo, most likely)."""
    known = _known_options()
    unknown = sorted(set(options) - known)
    if unknown:
        hints = [difflib.get_close_matches(u, known, n=1) for u in unknown]
        text = ", ".join(
            f"{u!r}" + (f" (did you mean {h[0]!r}?)" if h else "")
            for u, h in zip(unknown, hints, strict=True)
        )
        raise TypeError(
            f"unknown controller option(s) {text}; {name} takes "
            f"{', '.join(sorted(controller_options(name)))}"
        )


def options_for(name: str, options: Mapping[str, Any]) -> dict[str, Any]:
    """The entries of ``options`` that controller ``name`` takes, without the ``None``
    ones: for one set of options shared by several controllers (``fojax simulate
    --controller all --switching sat`` gives ``switching`` to the four sliding-mode
    laws and nothing to the FL). An option that no registered controller takes is
    still a ``TypeError``."""
    _unknown(name, options)
    own = controller_options(name)
    return {k: v for k, v in options.items() if k in own and v is not None}


def applied_options(names: Sequence[str], options: Mapping[str, Any]) -> dict[str, list[str]]:
    """For each option of ``options`` that is not ``None``: the controllers of ``names``
    that take it (possibly none), in the order of ``names``. What a study that shares
    one option set among several controllers records."""
    return {
        option: [name for name in names if option in controller_options(name)]
        for option, value in options.items()
        if value is not None
    }


def make_controller(name: str, **options: Any):
    """Controller ``name`` (a :class:`fojax.controllers.Cascade` around its law) with
    the configuration ``options``.

    Options are the law's fields (``dt``, ``horizon``, and e.g. ``switching``,
    ``fractional_method``) and the cascade's (``filter_frequency``,
    ``filter_damping``, ``thrust_floor``): :func:`controller_options`. ``None`` leaves
    the default. An option the controller does not take is a ``TypeError`` naming the
    controller and the options it takes (``switching`` for the FL, which has no
    switching function; a misspelt option, with the likely one); to configure several
    controllers from one set of options, pass each :func:`options_for` of it.
    """
    from fojax.controllers.cascade import Cascade

    cls = get_controller_class(name)
    _unknown(name, options)
    own, cascade = _fields(cls), _cascade_options()
    foreign = sorted(k for k, v in options.items() if v is not None and k not in own | cascade)
    if foreign:
        users = [n for n, c in _LAWS.items() if set(foreign) & _fields(c)]
        raise TypeError(
            f"controller {cls.name!r} takes no {', '.join(map(repr, foreign))} (taken by "
            f"{', '.join(users)}); {cls.name} takes {', '.join(sorted(own | cascade))}"
        )
    law = cls(**{k: v for k, v in options.items() if k in own and v is not None})
    return Cascade(law, **{k: v for k, v in options.items() if k in cascade and v is not None})
