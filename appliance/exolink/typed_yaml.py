"""exolink's YAML files into typed structs (msgspec), every error naming the file, the line and
the path inside the document (``nodes[2].params.speed``): the appliance config and the board's
settings are edited by lab engineers on a card, not by developers."""

from __future__ import annotations

import re
from typing import TypeVar

import msgspec
import yaml

T = TypeVar("T", bound=msgspec.Struct)


class ConfigError(Exception):
    """A configuration that must not be started; the message is for the operator."""


_PATH_RE = re.compile(r"`\$(?P<path>[^`]*)`")


def _friendly_path(msgspec_path: str) -> str:
    return msgspec_path.lstrip(".")


def line_of(root: yaml.Node | None, path: str) -> int | None:
    """Follow ``a.b[2].c`` through the composed YAML tree to report the line the operator edits."""
    node = root
    line = node.start_mark.line + 1 if node is not None else None
    for part in re.findall(r"\.?([^.\[\]]+)|\[(\d+)\]", path):
        key, index = part
        if isinstance(node, yaml.MappingNode) and key:
            match = next(((k, v) for k, v in node.value if getattr(k, "value", None) == key), None)
            if match is None:
                break
            key_node, node = match
            line = key_node.start_mark.line + 1  # the key's line, also when its value is a block
            continue
        elif isinstance(node, yaml.SequenceNode) and index:
            i = int(index)
            if i >= len(node.value):
                break
            node = node.value[i]
        else:
            break
        line = node.start_mark.line + 1
    return line


def error_at(source: str, root: yaml.Node | None, exc: msgspec.ValidationError) -> ConfigError:
    text = str(exc)
    m = _PATH_RE.search(text)
    path = _friendly_path(m.group("path")) if m else ""
    reason = _PATH_RE.sub("", text).replace(" - at ", "").strip()
    if "Object contains unknown field" in reason:
        field = reason.split("`")[1] if "`" in reason else "?"
        reason = f"unknown key {field!r}"
        path = f"{path}.{field}".lstrip(".")
    line = line_of(root, path) if path else None
    where = f"{source}:{line}" if line else source
    return ConfigError(f"{where}: {path or '(top level)'}: {reason}")


def decode_yaml(text: str, source: str, cls: type[T]) -> tuple[T, yaml.Node | None]:
    """Any of exolink's YAML files into its typed struct, with file:line:path errors."""
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
        data = yaml.safe_load(text)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = f":{mark.line + 1}" if mark else ""
        ctx = exc.context_mark
        where = f" ({exc.context} at line {ctx.line + 1})" if ctx and exc.context else ""
        raise ConfigError(f"{source}{line}: invalid YAML: {exc.problem or exc}{where}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{source}: invalid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(
            f"{source}: expected a mapping at the top level, got {type(data).__name__}"
        )
    _no_duplicate_keys(root, source)
    if "source" in cls.__struct_fields__:
        data["source"] = source
    try:
        return msgspec.convert(data, cls), root
    except msgspec.ValidationError as exc:
        raise error_at(source, root, exc) from None


def _no_duplicate_keys(node: yaml.Node | None, source: str) -> None:
    """PyYAML keeps the last of two equal keys without a word: an edit that adds a second
    ``heartbeat_deadline_ms`` further down would silently win. Refused, with both lines."""
    stack = [node] if node is not None else []
    while stack:
        n = stack.pop()
        if isinstance(n, yaml.MappingNode):
            seen: dict[str, int] = {}
            for k, v in n.value:
                key = getattr(k, "value", None)
                if isinstance(key, str):
                    if key in seen:
                        raise ConfigError(
                            f"{source}:{k.start_mark.line + 1}: duplicate key {key!r} "
                            f"(first at line {seen[key]})"
                        )
                    seen[key] = k.start_mark.line + 1
                stack.append(v)
        elif isinstance(n, yaml.SequenceNode):
            stack.extend(n.value)


def prefixed(exc: msgspec.ValidationError, prefix: str) -> msgspec.ValidationError:
    text = str(exc)
    text = text.replace("`$", f"`$.{prefix}", 1) if "`$" in text else f"{text} - at `$.{prefix}`"
    return msgspec.ValidationError(text)
