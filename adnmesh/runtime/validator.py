"""A small, fast validator for the JSON Schema subset the bus messages use.

:func:`compile_schema` turns a schema (draft 2020-12) into a Python function generated for it,
straight-line code with the checks inlined, because every message on the bus is validated and a
generic schema walker costs several microseconds per message. Supported keywords: ``type`` (one
or a list), ``const``, ``enum``, ``minimum``, ``maximum``, ``exclusiveMinimum``,
``exclusiveMaximum``, ``pattern``, ``properties``, ``required``, ``additionalProperties`` (bool
or schema), ``propertyNames``, ``minProperties``, ``prefixItems``, ``items``, ``minItems``,
``maxItems``; annotations (``$schema``, ``$id``, ``title``, ``description``) are ignored and any
other keyword is refused when compiling. Numbers follow JSON: ``number`` is a finite int or float
(not a bool), ``integer`` also accepts floats with no fractional part. Each check first tries
one expression true for the usual valid value (an object with exactly the fields of its schema,
a string already known to match its pattern) and runs the detailed checks, which raise with the
path of the problem, only when that fails. The test suite checks the
compiled functions against the reference implementation (``jsonschema``) on valid and invalid
payloads.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["SchemaViolation", "compile_schema"]

_ANNOTATIONS = {"$schema", "$id", "title", "description"}
_KEYWORDS = {"type", "const", "enum", "minimum", "maximum", "exclusiveMinimum",
             "exclusiveMaximum", "pattern", "properties", "required", "additionalProperties",
             "propertyNames", "minProperties", "prefixItems", "items", "minItems", "maxItems"}

_TYPE_TESTS = {
    "object": "type({x}) is dict",
    "array": "type({x}) is list",
    "string": "type({x}) is str",
    "boolean": "type({x}) is bool",
    "null": "{x} is None",
    "number": "(type({x}) is int or (type({x}) is float and {x} - {x} == 0.0))",
    "integer": "(type({x}) is int or (type({x}) is float and {x}.is_integer()))",
}


class SchemaViolation(ValueError):
    """A value does not match its schema.

    Attributes
    ----------
    path : str
        JSON path of the offending value, e.g. ``$.w.SGen1``.
    problem : str
        What is wrong.
    """

    def __init__(self, path: str, problem: str) -> None:
        super().__init__(f"{path}: {problem}")
        self.path = path
        self.problem = problem


class _Matches(dict):
    """Whether strings match one pattern, ``matches[text] -> bool``: searched once per string,
    then remembered (at most :data:`_MEMO_SIZE` strings of at most :data:`_MEMO_CHARS`
    characters). Bus messages repeat a few short strings (senders, DER ids) millions of times."""

    def __init__(self, pattern: str) -> None:
        super().__init__()
        self._search = re.compile(pattern).search

    def __missing__(self, text: str) -> bool:
        found = self._search(text) is not None
        if len(self) < _MEMO_SIZE and len(text) <= _MEMO_CHARS:
            self[text] = found
        return found


_MEMO_SIZE = 4096
_MEMO_CHARS = 64


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


class _Generator:
    def __init__(self) -> None:
        self.lines: list[str] = []
        self.names: dict[str, Any] = {"SchemaViolation": SchemaViolation, "_show": _show}
        self.counter = 0

    def const(self, value: Any) -> str:
        self.counter += 1
        name = f"C{self.counter}"
        self.names[name] = value
        return name

    def var(self) -> str:
        self.counter += 1
        return f"v{self.counter}"

    def emit(self, indent: int, line: str) -> None:
        self.lines.append("    " * indent + line)

    def fail(self, indent: int, path: str, problem: str) -> None:
        self.emit(indent, f"raise SchemaViolation({path}, {problem})")

    def fast(self, schema: Mapping, x: str) -> str | None:
        """A single expression true for the common valid values of a leaf ``schema`` (None if
        there is none); values it rejects go through the full checks, which raise or accept."""
        keys = set(schema) - _ANNOTATIONS
        bounds = [(schema[k], op) for k, op in (("minimum", ">="), ("maximum", "<="),
                                                ("exclusiveMinimum", ">"),
                                                ("exclusiveMaximum", "<")) if k in schema]
        limit = " and ".join(f"{x} {op} {self.const(b)}" for b, op in bounds)
        limit = f" and {limit}" if limit else ""
        if keys == {"const"}:
            return f"{x} == {self.const(schema['const'])} and type({x}) is " \
                   f"{type(schema['const']).__name__}"
        if keys == {"enum"} and all(type(v) is str for v in schema["enum"]):
            return f"type({x}) is str and {x} in {self.const(frozenset(schema['enum']))}"
        types = schema.get("type")
        if keys - {"type", "minimum", "maximum", "exclusiveMinimum", "exclusiveMaximum",
                   "pattern"}:
            return None
        if types == "number":
            return f"(type({x}) is float and {x} - {x} == 0.0 or type({x}) is int){limit}"
        if types == "integer":
            return f"type({x}) is int{limit}"
        if types == "boolean":
            return f"({x} is True or {x} is False)"
        if types == "string":
            if "pattern" in schema:
                matches = self.const(_Matches(schema["pattern"]))
                return f"type({x}) is str and {matches}[{x}]"
            return f"type({x}) is str"
        return None

    def check(self, schema: Mapping, x: str, path: str, indent: int) -> None:
        """Emit the checks of ``schema`` on the variable ``x`` (``path``: expression)."""
        unknown = set(schema) - _KEYWORDS - _ANNOTATIONS
        if unknown:
            raise ValueError(f"unsupported JSON Schema keyword(s): {', '.join(sorted(unknown))}")
        fast = self.fast(schema, x)
        if fast is not None:
            self.emit(indent, f"if not ({fast}):")
            indent += 1
            self.emit(indent, "pass")
        types = schema.get("type")
        if types is not None:
            names = [types] if isinstance(types, str) else list(types)
            test = " or ".join(_TYPE_TESTS[n].format(x=x) for n in names)
            self.emit(indent, f"if not ({test}):")
            self.fail(indent + 1, path, f"'must be {' or '.join(names)}, got ' + _show({x})")
        if "const" in schema:
            c = self.const(schema["const"])
            self.emit(indent, f"if {x} != {c} or type({x}) is not type({c}):")
            self.fail(indent + 1, path, f"'must be ' + repr({c}) + ', got ' + _show({x})")
        if "enum" in schema:
            c = self.const(tuple(schema["enum"]))
            self.emit(indent, f"if type({x}) is bool or {x} not in {c}:")
            self.fail(indent + 1, path, f"'must be one of ' + repr({c}) + ', got ' + _show({x})")
        bounds = []
        for key, op in (("minimum", ">="), ("maximum", "<="), ("exclusiveMinimum", ">"),
                        ("exclusiveMaximum", "<")):
            if key in schema:
                bounds.append(f"{x} {op} {self.const(schema[key])}")
        if bounds:
            self.emit(indent, f"if (type({x}) is int or type({x}) is float) and not "
                              f"({' and '.join(bounds)}):")
            self.fail(indent + 1, path, f"'out of range, got ' + _show({x})")
        if "pattern" in schema:
            c = self.const(re.compile(schema["pattern"]).search)
            text = self.const(schema["pattern"])
            self.emit(indent, f"if type({x}) is str and {c}({x}) is None:")
            self.fail(indent + 1, path, f"'must match ' + {text} + ', got ' + _show({x})")
        if any(k in schema for k in ("properties", "required", "additionalProperties",
                                     "propertyNames", "minProperties")):
            self.object(schema, x, path, indent)
        if any(k in schema for k in ("prefixItems", "items", "minItems", "maxItems")):
            self.array(schema, x, path, indent)

    def object(self, schema: Mapping, x: str, path: str, indent: int) -> None:
        self.emit(indent, f"if type({x}) is dict:")
        indent += 1
        self.emit(indent, "pass")
        required = schema.get("required", ())
        properties = schema.get("properties", {})
        extra = schema.get("additionalProperties", True)
        exact = extra is False and set(required) == set(properties) \
            and "minProperties" not in schema
        if exact:   # the usual case first: exactly the fields of the schema
            self.emit(indent, f"if {x}.keys() != {self.const(frozenset(required))}:")
            indent += 1
            self.emit(indent, "pass")
        if required:
            c = self.const(frozenset(required))
            self.emit(indent, f"if not {c} <= {x}.keys():")
            self.fail(indent + 1, path, f"'required field ' + repr(sorted({c} - {x}.keys())[0])"
                                        f" + ' is missing'")
        if schema.get("minProperties"):
            self.emit(indent, f"if len({x}) < {int(schema['minProperties'])}:")
            self.fail(indent + 1, path, f"'needs at least {schema['minProperties']} field(s)'")
        names = schema.get("propertyNames")
        if extra is False:
            c = self.const(frozenset(properties))
            self.emit(indent, f"if not {x}.keys() <= {c}:")
            self.fail(indent + 1, f"{path} + '.' + sorted({x}.keys() - {c})[0]",
                      "'unknown field'")
        if exact:
            indent -= 1
        for name, sub in properties.items():
            v = self.var()
            if name in required:   # present: checked above
                self.emit(indent, f"{v} = {x}[{name!r}]")
                self.check(sub, v, f"{path} + {'.' + name!r}", indent)
                continue
            self.emit(indent, f"{v} = {x}.get({name!r}, {x})")
            self.emit(indent, f"if {v} is not {x}:")
            self.emit(indent + 1, "pass")
            self.check(sub, v, f"{path} + {'.' + name!r}", indent + 1)
        if isinstance(extra, Mapping) or names:
            k, v = self.var(), self.var()
            self.emit(indent, f"for {k}, {v} in {x}.items():")
            self.emit(indent + 1, "pass")
            if names:
                self.check(names, k, f"{path} + '.' + str({k}) + ' (name)'", indent + 1)
            if isinstance(extra, Mapping):
                if properties:
                    c = self.const(frozenset(properties))
                    self.emit(indent + 1, f"if {k} in {c}:")
                    self.emit(indent + 2, "continue")
                self.check(extra, v, f"{path} + '.' + str({k})", indent + 1)

    def array(self, schema: Mapping, x: str, path: str, indent: int) -> None:
        self.emit(indent, f"if type({x}) is list:")
        indent += 1
        low, high = schema.get("minItems", 0), schema.get("maxItems")
        condition = f"len({x}) < {int(low)}" + (f" or len({x}) > {int(high)}" if high is not None
                                                 else "")
        self.emit(indent, f"if {condition}:")
        self.fail(indent + 1, path, f"'must have {low}..{high} items, got ' + str(len({x}))")
        for i, sub in enumerate(schema.get("prefixItems", ())):
            self.emit(indent, f"if len({x}) > {i}:")
            v = self.var()
            self.emit(indent + 1, f"{v} = {x}[{i}]")
            self.check(sub, v, f"{path} + '[{i}]'", indent + 1)
        items = schema.get("items")
        if isinstance(items, Mapping):
            i, v = self.var(), self.var()
            start = len(schema.get("prefixItems", ()))
            self.emit(indent, f"for {i}, {v} in enumerate({x}[{start}:], {start}):")
            self.emit(indent + 1, "pass")
            self.check(items, v, f"{path} + '[' + str({i}) + ']'", indent + 1)


def compile_schema(schema: Mapping, name: str = "check") -> Callable[[Any], None]:
    """Compile ``schema`` into ``check(value)``, which returns None or raises
    :class:`SchemaViolation`.

    Raises
    ------
    ValueError
        If the schema uses a keyword outside the supported subset.
    """
    gen = _Generator()
    gen.emit(0, f"def {name}(x0):")
    gen.emit(1, "pass")
    gen.check(schema, "x0", "'$'", 1)
    source = "\n".join(gen.lines) + "\n"
    namespace = dict(gen.names)
    exec(compile(source, f"<schema {name}>", "exec"), namespace)  # noqa: S102 - generated here
    function = namespace[name]
    function.source = source
    return function
