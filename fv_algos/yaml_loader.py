"""The YAML reader of scene, launch and parameter text: PyYAML's safe loader, with numbers as YAML 1.2
writes them, and a mapping that repeats a key refused."""
from __future__ import annotations

import re
from typing import Any

import yaml

_MERGE_TAG = "tag:yaml.org,2002:merge"


class YamlLoader(yaml.SafeLoader):
    """SafeLoader that also reads YAML 1.2's floats whose exponent has no sign or whose mantissa has no
    dot (1e9, -2E-3, 1.0e12, 1.5e3) as numbers: YAML 1.1, PyYAML's, reads them as text, so `fps:=1e9` was
    refused as "not of type float", and a scene's `mu: 1.0e12` as "not a finite number".

    A mapping that repeats a key is refused (YAML requires unique keys; PyYAML kept the last, so
    `{normal_N: 2.0, normal_N: 50.0}` pressed 50 N): a `yaml.constructor.ConstructorError` whose
    `problem_mark` is the repeated key and whose `problem` names it and the line of its first use.
    Keys brought in by a merge (`<<: *base`) may still be overridden.
    """

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        """The mapping of `node`, refusing a key its own entries repeat."""
        self.refuse_repeated_keys(node)
        return super().construct_mapping(node, deep=deep)

    def refuse_repeated_keys(self, node: yaml.MappingNode) -> None:
        """The ConstructorError above when `node`'s own entries repeat a key (call it before
        `flatten_mapping`, which adds the merged keys); a loader with its own mapping constructor
        calls it too."""
        first_line: dict[Any, int] = {}
        for key_node, _ in node.value:
            if key_node.tag == _MERGE_TAG:
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                seen = key in first_line
            except TypeError:  # an unhashable key: the mapping's constructor refuses it
                continue
            if seen:
                raise yaml.constructor.ConstructorError(
                    "while constructing a mapping", node.start_mark,
                    f"found duplicate key {key!r} (first on line {first_line[key]})", key_node.start_mark)
            first_line[key] = key_node.start_mark.line + 1


YamlLoader.add_implicit_resolver("tag:yaml.org,2002:float",
                                 re.compile(r"^[-+]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)[eE][-+]?[0-9]+$"),
                                 list("-+.0123456789"))
