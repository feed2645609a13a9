"""One parameter mechanism for every pipeline and component: strict pydantic models, deep-merged overrides.

* `Params` is the base of every parameter section: unknown keys are errors (``extra="forbid"``), values are
  type-checked strictly (no ``"yes"`` for a flag) and range-checked (``Field(gt=...)``), instances are immutable.
  ``Field(description=...)`` says what a parameter does and which paper table or section its default comes from.
* A nested section given as a partial mapping is merged into that field's *default* (not the nested class's
  defaults): ``{"iss": {"salient_radius": 2.0}}`` keeps a pipeline's ``iss.max_keypoints`` of 300.
* Building a `Params` (directly, with ``model_validate`` or with `resolve`) raises `ConfigError`; each message
  line names the dotted path of the bad key and, for an unknown key, the keys allowed there.
* Every integer parameter (``int`` or ``int | None``) has an upper bound: its own ``Field(le=...)`` where a count
  sets how much work or memory a run takes, else `MAX_INT` (10^9: a count beyond it is no count this machine can
  work through, and C libraries such as OpenCV take 32-bit ints). No float parameter takes NaN or infinity.
* `param_rows` lists every parameter (dotted path, value, type, description), for ``placerec pipelines NAME``.
"""

from __future__ import annotations

import contextvars
from collections.abc import Mapping
from typing import Any, TypeVar, get_args

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from placerec.errors import ConfigError, short_repr

__all__ = ["Params", "SectionError", "deep_merge", "resolve", "format_errors", "param_rows", "MAX_INT"]

#: the upper bound of every integer parameter that does not declare a tighter one
MAX_INT = 10**9
#: the constraint `Params` adds to such a field (pydantic's own ``le`` metadata)
_AT_MOST_MAX_INT = Field(le=MAX_INT).metadata

_MAX_REPR = 60
#: How many `Params` constructions are in progress: pydantic builds nested sections through their ``__init__``,
#: and only the outermost one turns a validation error into a `ConfigError` (with the full dotted path).
_DEPTH: contextvars.ContextVar[int] = contextvars.ContextVar("placerec_params_depth", default=0)


class Params(BaseModel):
    """Base of every parameter section (see the module docstring)."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)

    @classmethod
    def __pydantic_init_subclass__(cls, **kwargs: Any) -> None:
        """Give every integer field without an upper bound the bound `MAX_INT`."""
        super().__pydantic_init_subclass__(**kwargs)
        changed = False
        for field in cls.model_fields.values():
            ann = field.annotation
            if ann is int or set(get_args(ann)) == {int, type(None)}:
                if not any(hasattr(m, "le") or hasattr(m, "lt") for m in field.metadata):
                    field.metadata.extend(_AT_MOST_MAX_INT)
                    changed = True
        if changed:
            cls.model_rebuild(force=True)

    def __init__(self, **data: Any) -> None:
        token = _DEPTH.set(_DEPTH.get() + 1)
        try:
            super().__init__(**data)
        except ValidationError as exc:
            if _DEPTH.get() > 1:
                raise
            raise ConfigError(format_errors(exc, type(self), type(self).__name__)) from None
        finally:
            _DEPTH.reset(token)

    @classmethod
    def model_validate(cls, obj: Any, **kwargs: Any) -> Any:
        """As pydantic's, but an invalid ``obj`` is a `ConfigError` (as when the model is built directly)."""
        token = _DEPTH.set(_DEPTH.get() + 1)
        try:
            return super().model_validate(obj, **kwargs)
        except ValidationError as exc:
            if _DEPTH.get() > 1:
                raise
            raise ConfigError(format_errors(exc, cls, cls.__name__)) from None
        finally:
            _DEPTH.reset(token)

    def saved_dump(self) -> dict[str, Any]:
        """``model_dump(mode="json")`` without the run-time fields (``json_schema_extra={"runtime": True}``, e.g.
        a RAM budget): what a saved database records of its parameters, and what loading it compares."""
        out = self.model_dump(mode="json")
        for name, field in type(self).model_fields.items():
            if _is_runtime(field):
                out.pop(name, None)
            elif isinstance(value := getattr(self, name), Params):
                out[name] = value.saved_dump()
        return out

    @classmethod
    def without_runtime(cls, data: Any) -> Any:
        """``data`` (a saved dump) without the run-time fields, at every level: a database saved before a field
        became a run-time one compares equal to `saved_dump` again."""
        if not isinstance(data, Mapping):
            return data
        out = dict(data)
        for name, field in cls.model_fields.items():
            if _is_runtime(field):
                out.pop(name, None)
            elif (
                name in out
                and isinstance(model := _model_in(field.annotation), type)
                and issubclass(model, Params)
            ):
                out[name] = model.without_runtime(out[name])
        return out

    @model_validator(mode="before")
    @classmethod
    def _merge_sections(cls, data: Any) -> Any:
        """Merge partial mappings of nested sections into the field defaults."""
        if not isinstance(data, Mapping):
            return data
        out = dict(data)
        for name, field in cls.model_fields.items():
            value = out.get(name)
            if not isinstance(value, Mapping) or field.is_required():
                continue
            default = field.get_default(call_default_factory=True)
            if isinstance(default, Params) and type(default) is _model_in(field.annotation):
                out[name] = deep_merge(default.model_dump(), value)
        return out


def deep_merge(base: Mapping[str, Any], *overrides: Mapping[str, Any] | None) -> dict[str, Any]:
    """``base`` updated by each override in turn; mappings are merged key by key, other values replaced."""
    out = dict(base)
    for over in overrides:
        for key, value in (over or {}).items():
            if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
                out[key] = deep_merge(out[key], value)
            else:
                out[key] = value
    return out


P = TypeVar("P", bound="Params")


def resolve(cls: type[P], *layers: Mapping[str, Any] | None, where: str = "", path: str = "") -> P:
    """``cls`` built from ``layers`` (presets, then overrides) merged deeply; `ConfigError` otherwise.

    ``where`` names what is configured (e.g. a pipeline), ``path`` the config location of the parameters (e.g.
    ``pipelines[1].params``); both prefix every error line.
    """
    for layer in layers:
        if layer is not None and not isinstance(layer, Mapping):
            raise ConfigError(
                f"{where or cls.__name__}: {path or 'parameters'} must be a mapping, got {type(layer).__name__}"
            )
    token = _DEPTH.set(_DEPTH.get() + 1)
    try:
        return cls.model_validate(deep_merge({}, *layers))
    except ValidationError as exc:
        raise ConfigError(format_errors(exc, cls, where or cls.__name__, path)) from None
    finally:
        _DEPTH.reset(token)


def _is_runtime(field: Any) -> bool:
    """Whether a model field is a run-time one (``json_schema_extra={"runtime": True}``): not saved with results."""
    extra = field.json_schema_extra
    return isinstance(extra, dict) and bool(extra.get("runtime"))


def _model_in(annotation: Any) -> Any:
    """The pydantic model inside an annotation like ``X`` or ``X | None`` (else None)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in get_args(annotation):
        found = _model_in(arg)
        if found is not None:
            return found
    return None


def _allowed_keys(model: type[BaseModel], loc: tuple[Any, ...]) -> list[str]:
    """Field names of the section that ``loc`` (a pydantic error location without the bad key) points into."""
    current: Any = model
    for part in loc:
        if isinstance(part, int):
            continue
        field = current.model_fields.get(str(part)) if current is not None else None
        if field is None:
            return []
        current = _model_in(field.annotation)
    return sorted(current.model_fields) if current is not None else []


def _dotted(parts: tuple[Any, ...]) -> str:
    out = ""
    for p in parts:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out


class SectionError(ValueError):
    """Raised by a validator that validates a section itself (e.g. with a model chosen by a sibling key):
    carries that section's error lines, which `format_errors` prefixes with the section's path."""

    def __init__(self, exc: ValidationError, model: type[BaseModel], path: str) -> None:
        self.lines = error_lines(exc, model, path)
        super().__init__("; ".join(self.lines))


def error_lines(exc: ValidationError, model: type[BaseModel], path: str = "") -> list[str]:
    """One line per validation error: ``path.key: what was wrong`` (the allowed keys for an unknown one)."""
    lines: list[str] = []
    for err in exc.errors():
        loc = tuple(err["loc"])
        key = ".".join(x for x in (path, _dotted(loc)) if x)
        inner = (err.get("ctx") or {}).get("error")
        if isinstance(inner, SectionError):
            lines.extend(".".join(x for x in (key, line) if x) for line in inner.lines)
        elif err["type"] == "extra_forbidden":
            allowed = _allowed_keys(model, loc[:-1])
            lines.append(f"{key}: unknown key; allowed keys there: {', '.join(allowed)}")
        else:
            msg = err["msg"].removeprefix("Value error, ")
            got = "" if err["type"] == "value_error" else f" (got {short_repr(err.get('input'), _MAX_REPR)})"
            lines.append(f"{key}: {msg}{got}" if key else f"{msg}{got}")
    return lines


def format_errors(exc: ValidationError, model: type[BaseModel], where: str, path: str = "") -> str:
    """``where:`` and the `error_lines` of ``exc`` (one per line when there are several)."""
    lines = error_lines(exc, model, path)
    sep = "\n  " if len(lines) > 1 else " "
    return f"{where}:{sep}" + sep.join(lines)


def _type_name(annotation: Any) -> str:
    if isinstance(annotation, type):
        return annotation.__name__
    return str(annotation).replace("typing.", "").replace("NoneType", "None")


def param_rows(params: Params, prefix: str = "") -> list[tuple[str, Any, str, str]]:
    """(dotted path, value, type, description) of every leaf parameter of ``params``, nested sections expanded."""
    rows: list[tuple[str, Any, str, str]] = []
    for name, field in type(params).model_fields.items():
        value = getattr(params, name)
        key = f"{prefix}{name}"
        if isinstance(value, Params):
            rows.extend(param_rows(value, key + "."))
        else:
            rows.append((key, value, _type_name(field.annotation), field.description or ""))
    return rows
