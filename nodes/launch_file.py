"""Launch files: parse and validate a YAML launch file into `NodeSpec`s before anything
starts.

Format (every key but `nodes[].kind` optional)::

    args:                        # launch arguments, overridden by `fv launch FILE name:=value`
      rate_hz: 10.0              #   a default value
      topic: {default: /chatter, description: "where to talk"}
      robot: {description: "no default: must be given"}
    include:                     # other launch files, relative to this one
      - file: sensors.yaml
        args: {rate_hz: $(arg rate_hz)}
      - file: finger.yaml
        namespace: left          # its nodes' relative topics under /left, their names left_<name>
    nodes:
      - kind: talker             # a kind known to `nodes/registry.py`
        name: talker             # default: the kind; unique in the launch (with its namespace: left_talker)
        namespace: left          # its relative topics (`chatter` -> /left/chatter) and name (left_talker) under /left
        params: {rate_hz: $(arg rate_hz)}
        remap: {/chatter: /left/chatter}
        env: {OMP_NUM_THREADS: 1}
        respawn: true            # restart when it exits...
        respawn_delay: 1.0       # ...after this many seconds (default 1.0)
        max_retries: 5           # ...at most this often (default: no limit)
        standby: true            # keep a spare process, imports done, to take over at once
        required: false          # its final exit stops the whole launch

``$(arg name)`` is replaced by the argument's value: a whole-string substitution keeps the
value's YAML type (``rate_hz: $(arg rate_hz)`` stays a float), an embedded one is text.
A namespace, on a node or an include, works as in ROS: a relative one (``left``) goes under the
namespaces of the includes around it (an include under ``arm``: /arm/left), an absolute one (``/left``)
stands as written. A node in the namespace /arm/left is named ``arm_left_<name>``, its ROS-style path
(`fv param`) /arm/left/<name>.
Every error is a `LaunchError` naming the file, the line and the key.
"""
from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import yaml

from fv_algos.text_file import read_utf8
from fv_algos.yaml_loader import YamlLoader
from nodes.bus import absolute_namespace, namespaced_name, validate_topic
from nodes.params import ParamError, build_params, parse_text

TOP_KEYS = {"args", "include", "nodes"}
NODE_KEYS = {"kind", "name", "namespace", "params", "remap", "env", "respawn", "respawn_delay", "max_retries",
             "standby", "required"}
INCLUDE_KEYS = {"file", "args", "namespace"}
ARG_KEYS = {"default", "description"}
DEFAULT_RESPAWN_DELAY_S = 1.0
_ARG_RE = re.compile(r"\$\(arg ([A-Za-z_][A-Za-z0-9_]*)\)")
_NAMESPACE_RE = re.compile(r"/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*")
_NO_DEFAULT = object()


class LaunchError(ValueError):
    """A launch file that cannot run: names the file, the line and the key."""


class _Dict(dict):
    """A YAML mapping that remembers the line (1-based) of itself and of each key."""

    line: int = 0
    lines: dict


class _List(list):
    """A YAML sequence that remembers the line (1-based) of itself and of each item."""

    line: int = 0
    lines: list


class _Loader(YamlLoader):
    """SafeLoader whose mappings and sequences carry line numbers; duplicate keys fail."""


def _construct_mapping(loader: _Loader, node: yaml.MappingNode) -> _Dict:
    loader.refuse_repeated_keys(node)
    loader.flatten_mapping(node)
    out = _Dict()
    out.line, out.lines = node.start_mark.line + 1, {}
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)
        if not isinstance(key, str):
            raise yaml.constructor.ConstructorError(None, None, f"key {key!r} is not a string", key_node.start_mark)
        out[key] = loader.construct_object(value_node, deep=True)
        out.lines[key] = key_node.start_mark.line + 1
    return out


def _construct_sequence(loader: _Loader, node: yaml.SequenceNode) -> _List:
    out = _List(loader.construct_object(item, deep=True) for item in node.value)
    out.line, out.lines = node.start_mark.line + 1, [item.start_mark.line + 1 for item in node.value]
    return out


_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)
_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_SEQUENCE_TAG, _construct_sequence)


@dataclass
class NodeSpec:
    """One node of a launch, validated: what `fv node` needs plus the supervision policy.

    name: as `fv node list` shows it, its namespace's parts before its name in its launch file
    (left_camera). path: its ROS-style name (/left/camera). namespace: where its relative topics
    go (/left; "" for none).
    respawn_delay_s: seconds between an exit and the restart. max_retries: restarts
    allowed (None = no limit). standby: a respawning node keeps a spare process that has
    done its imports and takes over at once when the node exits. source: "file:line" of
    the entry, for messages. included_at: "file:line" of the include entry of the launch file loaded
    that brought it in ("" for a node of that file's own): one entry of an included file makes a node
    per include.
    """

    kind: str
    name: str
    path: str
    params: dict[str, Any] = field(default_factory=dict)
    remap: dict[str, str] = field(default_factory=dict)
    namespace: str = ""
    env: dict[str, str] = field(default_factory=dict)
    respawn: bool = False
    respawn_delay_s: float = DEFAULT_RESPAWN_DELAY_S
    max_retries: int | None = None
    standby: bool = False
    required: bool = False
    source: str = ""
    included_at: str = ""

    def argv(self) -> list[str]:
        """The `fv node` arguments that run this node (after `python -m nodes.cli`)."""
        out = ["node", self.kind, "--name", self.name, "--params-json", json.dumps(self.params)]
        if self.namespace:
            out += ["--ns", self.namespace]
        for src, dst in self.remap.items():
            out += ["--remap", f"{src}:={dst}"]
        return out


def _line(container: Any, key: Any, fallback: int) -> int:
    """Line of `key` in a YAML container (`fallback` for values made by substitution)."""
    lines = getattr(container, "lines", None)
    if isinstance(lines, dict):
        return lines.get(key, fallback)
    if isinstance(lines, list) and isinstance(key, int) and key < len(lines):
        return lines[key]
    return fallback


class _File:
    """Error helpers bound to one launch file."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def error(self, line: int, key: str, reason: str) -> LaunchError:
        return LaunchError(f"{self.path}:{line}: {key}: {reason}")

    def expect(self, value: Any, kind: type | tuple[type, ...], line: int, key: str, what: str) -> Any:
        kinds = kind if isinstance(kind, tuple) else (kind,)
        if not isinstance(value, kinds) or (isinstance(value, bool) and bool not in kinds):
            raise self.error(line, key, f"{value!r} is not {what}")
        return value

    def check_keys(self, mapping: _Dict, allowed: set[str], key: str) -> None:
        for name in mapping:
            if name not in allowed:
                raise self.error(mapping.lines[name], f"{key}.{name}" if key else name,
                                 f"unknown key; allowed: {sorted(allowed)}")


def load_yaml(path: Path) -> Any:
    """The file's YAML with line numbers; LaunchError (file and line) for bad YAML."""
    try:
        text = read_utf8(path)
    except OSError as exc:
        raise LaunchError(f"{path}: cannot read launch file: {exc.strerror}") from None
    except ValueError as exc:  # not UTF-8 (a launch file saved as Latin-1): named with its line
        raise LaunchError(str(exc)) from None
    try:
        return yaml.load(text, Loader=_Loader)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark is not None else 0
        raise LaunchError(f"{path}:{line}: bad YAML: {exc.problem or exc}") from None
    except yaml.YAMLError as exc:
        raise LaunchError(f"{path}: bad YAML: {exc}") from None


class CommandLineText(str):
    """A launch argument's value as typed on the command line, typed by `_resolve_args`."""


def parse_arg_overrides(items: list[str]) -> dict[str, Any]:
    """["name:=value", ...] from the command line -> {name: CommandLineText(value)}."""
    out: dict[str, Any] = {}
    for item in items:
        name, sep, value = item.partition(":=")
        if not sep or not name:
            raise LaunchError(f"launch argument {item!r} is not name:=value")
        out[name] = CommandLineText(value)
    return out


def typed_arg(text: CommandLineText, default: Any) -> Any:
    """A command-line argument's value: the text itself where the argument is text (its default is a
    string, or it has none: a node param of another type reads the text as YAML itself), else as YAML
    reads it ("0.5" -> 0.5, "false", "[1, 2]" -> list). Read as YAML, `device:=2` and `left:=0` (V4L2
    indices) were ints and refused, and a video path with " #" was cut there (the rest a comment)."""
    if isinstance(default, str) or default is _NO_DEFAULT:
        return str(text)
    return parse_text(text)


def load_launch(path: Path | str, args: dict[str, Any] | None = None, _stack: tuple[Path, ...] = (),
                _namespace: str = "", _included_at: str = "") -> list[NodeSpec]:
    """Validated node specs of launch file `path` (includes expanded) with `args` given, included under the
    absolute `_namespace` ("" for none) by the include entry at `_included_at` ("FILE:LINE"; "" for the file
    launched).

    Checks everything a node would check at start (kinds, param names and types, arg
    references), so a bad file fails before any process starts.
    """
    from nodes.registry import node_class  # imports node modules only when validating

    path = Path(path).resolve()
    f = _File(path)
    if path in _stack:
        raise LaunchError(f"{path}: included again by itself (include cycle: {' -> '.join(map(str, _stack))})")
    doc = load_yaml(path)
    if doc is None:
        doc = _Dict()
        doc.line, doc.lines = 1, {}
    if not isinstance(doc, _Dict):
        raise f.error(1, "(top level)", "a launch file is a mapping with keys args, include, nodes")
    f.check_keys(doc, TOP_KEYS, "")
    values = _resolve_args(f, doc, dict(args or {}), _included_at)
    specs: list[NodeSpec] = []
    for i, inc in enumerate(_section(f, doc, "include")):
        key = f"include[{i}]"
        line = _line(doc["include"], i, 1)
        inc = _substitute(f, f.expect(inc, _Dict, line, key, "a mapping with keys file, args, namespace"), values,
                          key)
        f.check_keys(inc, INCLUDE_KEYS, key)
        if "file" not in inc:
            raise f.error(line, f"{key}.file", "missing")
        target = path.parent / f.expect(inc["file"], str, inc.lines["file"], f"{key}.file", "a file name")
        inc_args = inc.get("args", {})
        f.expect(inc_args, dict, _line(inc, "args", line), f"{key}.args", "a mapping of argument values")
        if not target.is_file():
            raise f.error(inc.lines["file"], f"{key}.file", f"{target} does not exist")
        namespace = _entry_namespace(f, inc, f"{key}.namespace", line, _namespace)
        included = load_launch(target, inc_args, _stack + (path,), namespace, f"{path}:{line}")
        specs += [replace(spec, included_at=f"{path}:{line}") for spec in included]
    for i, entry in enumerate(_section(f, doc, "nodes")):
        key = f"nodes[{i}]"
        line = _line(doc["nodes"], i, 1)
        entry = _substitute(f, f.expect(entry, _Dict, line, key, "a mapping with at least `kind`"), values, key)
        specs.append(_node_spec(f, entry, line, key, node_class, _namespace))
    _check_unique(specs)
    return specs if _stack else _resolve_start_after(specs)


def _resolve_start_after(specs: list[NodeSpec]) -> list[NodeSpec]:
    """`specs` with each node's `start_after` names (a camera's, a bag player's: the nodes it waits for) resolved
    against the launch's nodes: a name of a node of the launch stands; else a name relative to the node's
    namespace (`tracker` in a file included under `left` is `left_tracker`, a node of that file) becomes that
    node's name. LaunchError naming the entry for a name that is neither: such a camera waited its whole
    `start_timeout_s` (30 s) for a node that never came (`pipeline.yaml` included under a namespace)."""
    names = {spec.name for spec in specs}
    out = []
    for spec in specs:
        awaited = spec.params.get("start_after")
        if not awaited:
            out.append(spec)
            continue
        resolved = []
        for name in awaited:
            relative = namespaced_name(spec.namespace, name)
            if name not in names and relative not in names:
                raise LaunchError(f"{spec.source}: {spec.name}'s start_after names {name!r}, no node of this launch "
                                  f"(its nodes: {', '.join(sorted(names))})")
            resolved.append(name if name in names else relative)
        out.append(replace(spec, params={**spec.params, "start_after": resolved}))
    return out


def _entry_namespace(f: _File, entry: _Dict, key: str, line: int, outer: str) -> str:
    """The absolute namespace a node or include entry puts its nodes in, as ROS resolves it: a relative
    `namespace` goes under `outer`, the namespace its file is included under ("left" in "/arm" ->
    "/arm/left"); an absolute one stands ("/left" -> "/left"); none is `outer`."""
    value = f.expect(entry.get("namespace", ""), str, entry.lines.get("namespace", line), key, "a namespace")
    if value and not _NAMESPACE_RE.fullmatch(value):
        raise f.error(entry.lines.get("namespace", line), key,
                      f"{value!r} is not a namespace (names of letters, digits and _ joined by /)")
    return absolute_namespace(value) if value.startswith("/") else outer + absolute_namespace(value)


def _section(f: _File, doc: _Dict, name: str) -> _List:
    value = doc.get(name)
    if value is None:
        out = _List()
        out.line, out.lines = doc.lines.get(name, 1), []
        return out
    return f.expect(value, _List, doc.lines[name], name, "a list")


def _resolve_args(f: _File, doc: _Dict, given: dict[str, Any], included_at: str) -> dict[str, Any]:
    """The values of the arguments `doc` declares, from `given` or their defaults; `included_at` ("FILE:LINE" of the
    include entry that gives them, "" for the file launched) is named in the errors: the command-line hint of an
    included file's missing argument was refused as undeclared where it was followed."""
    declared = doc.get("args") or _Dict()
    f.expect(declared, dict, doc.lines.get("args", 1), "args", "a mapping of argument names to defaults")
    by = f" by the include entry at {included_at}" if included_at else ""
    for name in given:
        if name not in declared:
            raise LaunchError(f"{f.path}: argument {name!r} given{by} but not declared; declared: {sorted(declared)}")
    values = {}
    for name, spec in declared.items():
        key, line = f"args.{name}", declared.lines[name]
        default = spec
        if isinstance(spec, _Dict):
            f.check_keys(spec, ARG_KEYS, key)
            default = spec.get("default", _NO_DEFAULT)
        value = given.get(name, default)
        if isinstance(value, CommandLineText):
            value = typed_arg(value, default)
        if value is _NO_DEFAULT:
            hint = (f"give it in the args of the include entry at {included_at}" if included_at
                    else f"fv launch {f.path.name} {name}:=VALUE")
            raise f.error(line, key, f"no default and not given ({hint})")
        values[name] = value
    return values


def _substitute(f: _File, value: Any, args: dict[str, Any], key: str, line: int = 0) -> Any:
    """`value` with every `$(arg name)` replaced; keeps line numbers of containers."""
    if isinstance(value, _Dict):
        out = _Dict()
        out.line, out.lines = value.line, {}
        for k, v in value.items():  # a key too (`remap: {$(arg topic): /other}` was kept as written)
            name = str(_substitute(f, k, args, f"{key}.{k}", value.lines[k])) if isinstance(k, str) else k
            out[name] = _substitute(f, v, args, f"{key}.{name}", value.lines[k])
            out.lines[name] = value.lines[k]
        return out
    if isinstance(value, _List):
        out_list = _List(_substitute(f, v, args, f"{key}[{i}]", value.lines[i]) for i, v in enumerate(value))
        out_list.line, out_list.lines = value.line, value.lines
        return out_list
    if not isinstance(value, str) or "$(" not in value:
        return value
    for name in _ARG_RE.findall(value):
        if name not in args:
            raise f.error(line, key, f"$(arg {name}) is not declared under args; declared: {sorted(args)}")
    whole = _ARG_RE.fullmatch(value)
    if whole:
        return args[whole.group(1)]
    out_text = _ARG_RE.sub(lambda m: str(args[m.group(1)]), value)
    if "$(" in out_text:
        raise f.error(line, key, f"{value!r}: only $(arg NAME) substitutions are known")
    return out_text


def _node_spec(f: _File, entry: _Dict, line: int, key: str, node_class: Any, outer: str) -> NodeSpec:
    """The node of `entry`, in its file included under the absolute namespace `outer`."""
    f.check_keys(entry, NODE_KEYS, key)
    lines = entry.lines
    if "kind" not in entry:
        raise f.error(line, f"{key}.kind", "missing")
    kind = f.expect(entry["kind"], str, lines["kind"], f"{key}.kind", "a node kind")
    try:
        cls = node_class(kind)
    except KeyError as exc:
        raise f.error(lines["kind"], f"{key}.kind", exc.args[0]) from None
    name = f.expect(entry.get("name", kind), str, lines.get("name", line), f"{key}.name", "a node name")
    if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_\-]*", name):
        raise f.error(lines.get("name", line), f"{key}.name", f"{name!r} is not a name (letters, digits, _ and -)")
    key = f"{key} ({name})"
    params = f.expect(entry.get("params", {}), dict, lines.get("params", line), f"{key}.params", "a mapping")
    try:
        build_params(cls.Params, params, where=f"node kind {kind!r}")
    except ParamError as exc:
        at = _line(params, exc.key, lines.get("params", line))
        raise f.error(at, f"{key}.params" + (f".{exc.key}" if exc.key else ""), str(exc)) from None
    for pname, pvalue in params.items():
        try:
            json.dumps(pvalue, allow_nan=True)
        except (TypeError, ValueError):
            raise f.error(_line(params, pname, line), f"{key}.params.{pname}",
                          f"{pvalue!r} is not a plain YAML value (number, text, list, mapping)") from None
    remap = f.expect(entry.get("remap", {}), dict, lines.get("remap", line), f"{key}.remap", "a mapping FROM: TO")
    for src, dst in remap.items():  # checked here, not as the node starts (the launch then stopped, `--check` passed)
        at = _line(remap, src, line)
        f.expect(src, str, at, f"{key}.remap", "a topic name")
        f.expect(dst, str, at, f"{key}.remap.{src}", "a topic name")
        if not src.strip() or " " in src or "\0" in src:
            raise f.error(at, f"{key}.remap", f"{src!r} is not a topic name")
        try:
            validate_topic(dst)
        except ValueError as exc:
            raise f.error(at, f"{key}.remap.{src}", f"{exc} (a remap's target is an absolute topic)") from None
    env = f.expect(entry.get("env", {}), dict, lines.get("env", line), f"{key}.env", "a mapping NAME: value")
    for var, val in env.items():
        at = _line(env, var, line)
        f.expect(val, (str, int, float), at, f"{key}.env.{var}", "text or a number")
        if not isinstance(var, str) or not re.fullmatch(r"[^=\0]+", var):
            raise f.error(at, f"{key}.env", f"{var!r} is not an environment variable name (no '=' or NUL)")
        if "\0" in str(val):
            raise f.error(at, f"{key}.env.{var}", "a value holds no NUL character")
    delay = f.expect(entry.get("respawn_delay", DEFAULT_RESPAWN_DELAY_S), (int, float),
                     lines.get("respawn_delay", line), f"{key}.respawn_delay", "a number of seconds")
    if not math.isfinite(delay) or delay < 0:
        raise f.error(lines["respawn_delay"], f"{key}.respawn_delay", f"{delay} s is not >= 0")
    retries = entry.get("max_retries")
    if retries is not None:
        f.expect(retries, int, lines["max_retries"], f"{key}.max_retries", "a whole number")
        if retries < 0:
            raise f.error(lines["max_retries"], f"{key}.max_retries", f"{retries} is not >= 0")
    respawn = f.expect(entry.get("respawn", False), bool, lines.get("respawn", line), f"{key}.respawn",
                       "true or false")
    standby = f.expect(entry.get("standby", False), bool, lines.get("standby", line), f"{key}.standby",
                       "true or false")
    if standby and not respawn:
        raise f.error(lines["standby"], f"{key}.standby", "a standby process needs respawn: true")
    namespace = _entry_namespace(f, entry, f"{key}.namespace", line, outer)
    return NodeSpec(
        kind=kind, name=namespaced_name(namespace, name), path=f"{namespace}/{name}", params=dict(params),
        remap=dict(remap), namespace=namespace,
        env={var: str(val) for var, val in env.items()},
        respawn=respawn, respawn_delay_s=float(delay), max_retries=retries, standby=standby,
        required=f.expect(entry.get("required", False), bool, lines.get("required", line), f"{key}.required",
                          "true or false"),
        source=f"{f.path}:{line}")


def _check_unique(specs: list[NodeSpec]) -> None:
    """LaunchError naming both nodes where two nodes of one launch file (its own or included) get one name
    (/left/camera and /left_camera are both left_camera), each at its place in that file: its entry, or for
    an included node the include entry it came through, with its entry in the included file. One entry of a
    file included twice makes both nodes; a clash inside an included file was refused there, so two included
    nodes come through two include entries and no place is named twice."""
    seen: dict[str, NodeSpec] = {}
    for spec in specs:
        first = seen.setdefault(spec.name, spec)
        if first is not spec:
            own = f", entry {spec.source}" if spec.included_at else ""
            their = "" if not first.included_at else (
                ", the same entry" if first.source == spec.source else f", entry {first.source}")
            raise LaunchError(f"{_place(spec)}: name: node name {spec.name!r} ({spec.path}{own}) is already used at "
                              f"{_place(first)} ({first.path}{their})")


def _place(spec: NodeSpec) -> str:
    """"file:line" of a node in the launch file being checked: the include entry it came through, or its
    own entry."""
    return spec.included_at or spec.source
